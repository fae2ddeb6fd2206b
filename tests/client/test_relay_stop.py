"""`gcdtrav relay` stopped while frames, credits and outputs flow (issue 36: `RuntimeError: Already borrowed`
in close(), 1 stop in 3). zenoh-python's entities are pyo3 objects: ``put`` borrows the publisher while it
waits for zenoh with the GIL released, ``undeclare`` borrows it mutably, so an undeclare while a zenoh
callback's put is under way raises. Stopped here over and over, with a fake service flooding the link."""

from __future__ import annotations

import threading
import time

import numpy as np
import zenoh
from gcdtrav.client.relay.relay import Relay
from gcdtrav.client.session.zenoh_args import zenoh_config
from gcdtrav.schemas.images import encode_jpeg
from gcdtrav.schemas.messages import CreditGrant, ImageEnvelope, PixelEncoding
from gcdtrav.schemas.relay import RelaySettings
from zenoh_helpers import connecting_config, free_port, wait_until

SOURCE, CAMERA_KEY = "r1/front", "robot/camera/front"
OUTPUT = b"\x81\xa6header\x81\xa5stamp\xcb" + bytes(8) + bytes(300_000)  # {"header": {"stamp": 0.0}} + padding


def flood(stop: threading.Event, session: zenoh.Session, key: str, payload: bytes) -> threading.Thread:
    publisher = session.declare_publisher(key)

    def run() -> None:
        while not stop.is_set():
            publisher.put(payload)
            time.sleep(0.0005)
        publisher.undeclare()

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def test_a_relay_stops_cleanly_while_everything_flows() -> None:
    service_port, robot_port = free_port(), free_port()
    service = zenoh.open(zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{service_port}"], multicast_scouting=False))
    bus = zenoh.open(zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{robot_port}"], multicast_scouting=False))
    link = zenoh.open(connecting_config(service_port, mode="client"))
    local = zenoh.open(connecting_config(robot_port, mode="client"))
    image = np.full((48, 64, 3), 90, np.uint8)
    frame = ImageEnvelope(stamp=time.time(), encoding=PixelEncoding.JPEG, width=64, height=48, data=encode_jpeg(image))
    grant = CreditGrant(
        source=SOURCE, instance="fake", grant=0, reason="taken", granted_at=time.time(), model_input=(64, 48),
        max_frame_age_s=None,
    )  # fmt: skip
    stop = threading.Event()
    floods = [
        flood(stop, bus, CAMERA_KEY, frame.pack()),  # the camera
        flood(stop, service, f"gcdtrav/credit/{SOURCE}", grant.pack()),  # credits, far more than a service grants
        flood(stop, service, f"gcdtrav/out/{SOURCE}/maps8", OUTPUT),  # outputs
    ]
    consumer = bus.declare_subscriber(f"gcdtrav/out/{SOURCE}/maps8", lambda sample: None)
    settings = RelaySettings.model_validate(
        {"cameras": [{"camera": CAMERA_KEY, "source": SOURCE}], "forward": ["maps8"], "health_period_s": 0.01}
    )
    try:
        for _ in range(20):
            relay = Relay(settings, link, local).start()
            assert wait_until(lambda r=relay: r.forwarders[0].active and r.forwarders[0].downlink.total > 0, 30)
            assert wait_until(lambda r=relay: r.camera(SOURCE).sent > 0, 30), "nothing sent"
            relay.close()  # raised RuntimeError: Already borrowed
            assert not relay.forwarders[0].active
    finally:
        stop.set()
        for thread in floods:
            thread.join(5)
        consumer.undeclare()
        for session in (local, link, bus, service):
            session.close()


def test_close_while_a_callback_forwards_an_output() -> None:
    """The race itself, made likely: zenoh's callback thread keeps forwarding a real output sample while the
    relay closes. Before, close() raised RuntimeError('Already borrowed') (the callback's put held the
    publisher), and the callback then put on an undeclared publisher; now close waits for the put under way
    and later callbacks are skipped."""
    service_port, robot_port = free_port(), free_port()
    service = zenoh.open(zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{service_port}"], multicast_scouting=False))
    bus = zenoh.open(zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{robot_port}"], multicast_scouting=False))
    link = zenoh.open(connecting_config(service_port, mode="client"))
    local = zenoh.open(connecting_config(robot_port, mode="client"))
    samples: list[zenoh.Sample] = []
    capture = link.declare_subscriber(f"gcdtrav/out/{SOURCE}/maps8", samples.append)
    settings = RelaySettings.model_validate(
        {"cameras": [{"camera": CAMERA_KEY, "source": SOURCE}], "forward": ["maps8"]}
    )
    try:
        assert wait_until(lambda: service.put(f"gcdtrav/out/{SOURCE}/maps8", OUTPUT) or bool(samples), 30)
        sample = samples[0]
        for _ in range(20):
            relay = Relay(settings, link, local).start()
            forwarder = relay.forwarders[0]
            errors: list[BaseException] = []
            stop = threading.Event()

            def deliver(forwarder=forwarder, errors=errors, stop=stop) -> None:  # type: ignore[no-untyped-def]
                while not stop.is_set():
                    try:
                        forwarder._arrived(sample)
                    except BaseException as err:  # what zenoh's callback thread would swallow
                        errors.append(err)
                        return

            thread = threading.Thread(target=deliver, daemon=True)
            thread.start()
            assert wait_until(lambda forwarder=forwarder: forwarder.downlink.total > 0, 30)
            relay.close()
            stop.set()
            thread.join(5)
            assert errors == []
    finally:
        capture.undeclare()
        for session in (local, link, bus, service):
            session.close()
