"""The service end to end through the client, on real zenoh sessions over loopback."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import zenoh
from conftest import TINY_INPUT_SIZE, textured_image
from zenoh_helpers import (
    connecting_config,
    service_reachable,
    subscribed_elsewhere,
    wait_until,
)

pytest.importorskip("torch")

from gcdtrav.client import AnchorSetRejected, Maps, ServiceError, TraversabilityClient
from gcdtrav.schemas.anchors import default_anchor_set
from gcdtrav.schemas.keys import input_key
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.backends.cpus import usable_cpus
from gcdtrav.service.bus.node import TraversabilityService
from gcdtrav.service.engine import gcd

from tools.loopback import anchor_set_at_start, in_process_service

TWO_ANCHORS = {
    "name": "puddles",
    "anchors": [{"concept": "puddle", "position": 0.0}, {"concept": "road", "position": 1.0, "width": 0.05}],
}


class SlowBackend:
    """Wraps a backend and sleeps before each frame: a CPU box slower than the robots."""

    def __init__(self, inner, delay: float) -> None:  # type: ignore[no-untyped-def]
        self.inner, self.delay, self.model_id = inner, delay, inner.model_id

    def describe(self):  # type: ignore[no-untyped-def]
        return self.inner.describe()

    def prepare(self, concepts):  # type: ignore[no-untyped-def]
        return self.inner.prepare(concepts)

    def logits(self, image, prepared):  # type: ignore[no-untyped-def]
        time.sleep(self.delay)
        return self.inner.logits(image, prepared)


@dataclass
class Running:
    service: TraversabilityService
    client: TraversabilityClient
    settings: ServiceSettings
    received: list[Maps]


@contextmanager
def started_service(backend, state_dir: Path, **settings_kw: object) -> Iterator[tuple[TraversabilityService, int]]:  # type: ignore[no-untyped-def]
    settings_kw.setdefault("max_frame_age_s", None)  # some frames are stamped in 1970
    settings_kw.setdefault("reuse", {"enabled": False})  # one image again and again: inferred each time here
    settings = ServiceSettings(state_dir=state_dir, instance="test-1", **settings_kw)  # type: ignore[arg-type]
    with in_process_service(backend, settings, anchor_set_at_start(settings)) as started:
        yield started


# threads=None: torch has every CPU, one thread does all per-frame work. threads=1 on a box with more CPUs:
# outputs of frame n are published by a second thread while frame n + 1 is inferred.
PIPELINES = [
    pytest.param(None, id="serial"),
    pytest.param(1, id="overlapped", marks=pytest.mark.skipif(usable_cpus() < 2, reason="needs 2 CPUs")),
]


@pytest.fixture(params=PIPELINES)
def running(tiny_backend, tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[Running]:  # type: ignore[no-untyped-def]
    with started_service(
        tiny_backend, tmp_path, history=3, max_payload_bytes=300_000, full_resolution=True, threads=request.param
    ) as (service, port):
        assert service.runtime.worker.overlap_outputs == (request.param is not None)
        client = TraversabilityClient(config=connecting_config(port), timeout=5.0)
        received: list[Maps] = []
        subscriber = client.subscribe_maps("**", received.append)
        assert wait_until(lambda: service_reachable(client), 60)
        assert subscribed_elsewhere(service.session, service.keys.maps("probe")), "the maps subscription"
        yield Running(service, client, service.settings, received)
        subscriber.undeclare()
        client.close()


def publish_and_wait(run: Running, source: str, image: np.ndarray, **kw: object) -> Maps:
    before = len(run.received)
    run.client.publish_image(source, image, **kw)  # type: ignore[arg-type]
    assert wait_until(lambda: len(run.received) > before, 60), (  # the bound of a failure only
        f"no maps received; the service's counts of {source}: {run.service.status().sources.get(source)}"
    )
    return run.received[-1]


def publish_and_process(run: Running, source: str, image: np.ndarray, **kw: object) -> None:
    """Publish a frame and wait until the service has processed it (its queries answer from it). Not its maps:
    maps go out with congestion control DROP, and a loaded machine may drop large ones (full resolution) on the
    way, as the service means to."""
    counts = run.service.status().sources.get(source)
    before = 0 if counts is None else counts.processed
    run.client.publish_image(source, image, **kw)  # type: ignore[arg-type]

    def processed() -> bool:
        counts = run.service.status().sources.get(source)
        return counts is not None and counts.processed > before

    assert wait_until(processed, 60), f"not processed; the service's counts: {run.service.status().sources}"


def test_image_in_maps_out_with_header(running: Running) -> None:
    image = textured_image(120, 160)
    maps = publish_and_wait(running, "r1/front", image, stamp=1234.5, frame_id="front_cam", compression="png")
    h = maps.header
    assert (h.source, h.key, h.seq, h.stamp, h.frame_id) == ("r1/front", "gcdtrav/in/r1/front", 0, 1234.5, "front_cam")
    assert h.map_shape == (TINY_INPUT_SIZE, TINY_INPUT_SIZE) and h.image_size == (160, 120)
    assert h.scale == pytest.approx((160 / TINY_INPUT_SIZE, 120 / TINY_INPUT_SIZE))
    assert h.anchor_set_version == default_anchor_set().version and h.method.value == "gcd"
    assert h.instance == "test-1" and h.inference_ms > 0 and h.received_at <= h.published_at
    assert maps.traversability.shape == maps.uncertainty.shape == (TINY_INPUT_SIZE, TINY_INPUT_SIZE)
    assert maps.traversability_full is not None and maps.traversability_full.shape == (120, 160)
    # The maps are the engine's, quantised to 1/65535.
    backend = running.service.pipeline.backend
    cas = default_anchor_set()
    weights = gcd.softmax_weights(backend.logits(image, backend.prepare(cas.concepts)))
    t, u = gcd.mixture_mean_std(weights, cas.positions, cas.widths)
    np.testing.assert_allclose(maps.traversability, t, atol=1 / 65535)
    np.testing.assert_allclose(maps.uncertainty, u, atol=1 / 65535)
    # The robot's clock goes on from its own stamp (a jump of decades would be a clock step, learnt once it holds).
    second = publish_and_wait(running, "r1/front", image, stamp=1235.0)
    assert second.header.seq == 1 and second.header.stamp == 1235.0


def test_patch_and_region_queries_match_the_engine(running: Running) -> None:
    image = textured_image(96 * 2, 96 * 3, seed=5)  # scale (3, 2): pixel (x, y) -> cell (y // 2, x // 3)
    publish_and_process(running, "r2", image, compression="png")
    backend = running.service.pipeline.backend
    cas = default_anchor_set()
    weights = gcd.softmax_weights(backend.logits(image, backend.prepare(cas.concepts)))

    reply = running.client.patch("r2", x=100, y=61)
    assert reply.patch == (30, 33) and reply.seq == 0 and reply.anchor_set_version == cas.version
    expected = weights[:, 30, 33]
    np.testing.assert_allclose(reply.weights, expected, atol=2e-3)
    stats = gcd.mixture_statistics(expected[:, None], cas.positions, cas.widths)
    assert reply.mean == pytest.approx(float(stats.mean[0]), abs=2e-3)
    assert reply.std == pytest.approx(float(stats.std[0]), abs=2e-3)
    assert [a.concept for a in reply.anchors] == cas.concepts
    assert len(reply.density) == len(reply.density_x) == gcd.DEFAULT_DENSITY_GRID

    by_index = running.client.patch_by_index("r2", i=30, j=33)
    assert by_index.weights == reply.weights
    with pytest.deprecated_call():  # the old name still answers, with a warning
        assert running.client.patch_cell("r2", 30, 33).weights == reply.weights

    region = running.client.region("r2", 30, 20, 60, 40)  # cells i 10..19, j 10..19
    assert region.region == (10, 10, 20, 20)
    np.testing.assert_allclose(region.weights, weights[:, 10:20, 10:20].mean(axis=(1, 2)), atol=2e-3)


def test_query_errors_are_clear(running: Running) -> None:
    publish_and_process(running, "r3", textured_image(50, 50))
    client = running.client
    cases = [
        (lambda: client.patch("nobody", 1, 1), "unknown source 'nobody'"),
        (lambda: client.patch("r3", 50, 10), "outside the 50x50 image"),
        (lambda: client.patch("r3", 1, 1, seq=7), "seq 7 of 'r3' is not kept"),
        (lambda: client.patch_by_index("r3", -1, 0), "outside the"),
        (lambda: client.region("r3", 10, 10, 5, 20), "region"),
        (
            lambda: client._query("gcdtrav/out/r3/patch", type(client.patch("r3", 1, 1)), {"x": "abc", "y": 1}),
            "not a number",
        ),
        (lambda: client._query("gcdtrav/out/r3/patch", type(client.patch("r3", 1, 1)), {"x": 1}), "exactly one"),
        (lambda: client._query("gcdtrav/out/r3/patch", type(client.patch("r3", 1, 1)), {"q": 1}), "unknown param"),
    ]
    for call, message in cases:
        with pytest.raises(ServiceError, match=message):
            call()
    assert running.service.status().rejected_by_reason["bad_query"] == len(cases)


def test_history_keeps_the_last_frames(running: Running) -> None:
    for _ in range(4):
        publish_and_wait(running, "r4", textured_image(40, 40))
    assert running.client.patch("r4", 1, 1, seq=3).seq == 3
    assert running.client.patch("r4", 1, 1, seq=1).seq == 1
    with pytest.raises(ServiceError, match=r"kept: 1\.\.3"):
        running.client.patch("r4", 1, 1, seq=0)


def test_anchor_swap_applies_to_the_next_frames_and_persists(running: Running) -> None:
    old = running.client.anchors()
    assert old.version == default_anchor_set().version and len(old.anchor_set) == 13
    publish_and_wait(running, "r5", textured_image(64, 64))
    version = running.client.set_anchors(TWO_ANCHORS)
    assert version != old.version and running.client.anchors().version == version
    maps = publish_and_wait(running, "r5", textured_image(64, 64))
    assert maps.header.anchor_set_version == version
    latest = running.client.patch("r5", 3, 3)
    assert len(latest.weights) == 2 and latest.anchor_set_version == version
    earlier = running.client.patch("r5", 3, 3, seq=0)  # kept frames keep the set they were made with
    assert len(earlier.weights) == 13 and earlier.anchor_set_version == old.version
    # The accepted set is on disk and a restarted service starts with it.
    assert anchor_set_at_start(running.settings).version == version


def test_invalid_anchor_set_is_rejected_and_the_old_one_stays(running: Running) -> None:
    before = running.client.anchors().version
    bad = {"anchors": [{"concept": "grass", "position": 0.5}, {"concept": "water", "position": 1.2}], "x": 1}
    with pytest.raises(AnchorSetRejected) as info:
        running.client.set_anchors(bad)
    assert any("outside [0, 1]" in m for m in info.value.messages)
    assert any("unknown field" in m for m in info.value.messages)
    assert info.value.active_version == before
    with pytest.raises(AnchorSetRejected, match="not valid JSON or YAML"):
        running.client.set_anchors("{ not json")
    assert running.client.anchors().version == before
    assert not running.settings.state_file.exists()
    maps = publish_and_wait(running, "r6", textured_image(32, 32))
    assert maps.header.anchor_set_version == before


def test_bad_payloads_are_counted_and_the_next_frame_processed(running: Running) -> None:
    session = running.client.session
    key = "gcdtrav/in/bad"

    def rejected() -> int:
        source = running.service.status().sources.get("bad")
        return source.rejected if source is not None else 0

    payloads = [
        (b"\xff\xd8\xff garbage", zenoh.Encoding.IMAGE_JPEG),
        (b"\x85not msgpack", zenoh.Encoding("application/msgpack")),
        (b"x" * 400_000, zenoh.Encoding.ZENOH_BYTES),  # over the 300 kB limit of this fixture
        (b"", zenoh.Encoding.ZENOH_BYTES),
    ]
    # A source takes its slot with a frame that decodes (garbage from a new name is counted by reason only):
    assert publish_and_wait(running, "bad", textured_image(48, 48)).header.source == "bad"
    for count, (payload, encoding) in enumerate(payloads, start=1):
        session.put(key, payload, encoding=encoding)
        # One at a time: two frames in the latest-only queue at once would count one as dropped.
        assert wait_until(lambda count=count: rejected() == count, 60)
    maps = publish_and_wait(running, "bad", textured_image(48, 48))
    assert maps.header.source == "bad"
    status = running.client.status()
    counts = status.sources["bad"]
    assert (counts.received, counts.rejected, counts.processed) == (6, 4, 2)
    for reason in ("undecodable", "malformed_envelope", "oversized", "empty"):
        assert status.rejected_by_reason[reason] == 1
    assert len(status.last_errors) == 4 and status.uptime_s > 0


@pytest.mark.parametrize("threads", PIPELINES)
def test_latest_only_under_load(tiny_backend, tmp_path: Path, threads: int | None) -> None:  # type: ignore[no-untyped-def]
    with started_service(SlowBackend(tiny_backend, 0.08), tmp_path, threads=threads) as (service, port):
        client = TraversabilityClient(config=connecting_config(port), timeout=5.0)
        try:
            assert wait_until(lambda: service_reachable(client), 60)
            # the service's input subscription known to the client: none of the burst is held back
            assert subscribed_elsewhere(client.session, input_key(client.input_prefix, "burst")), "the inputs"
            image = textured_image(64, 64)
            queued = []
            for index in range(50):
                client.publish_image("burst", image)
                if index % 10 == 0:
                    client.publish_image("steady", image)
                queued.append(len(service.runtime.queue))
                time.sleep(0.005)
            assert max(queued) <= 4  # per source the newest arrival and the newest ready frame, whatever the rate

            def all_in_and_done() -> bool:  # every frame sent has arrived (50 + 5) and none is queued or in flight
                sources = service.status().sources
                arrived = sum(s.received for s in sources.values())
                return arrived >= 55 and len(service.runtime.queue) == 0 and not _busy(service)

            assert wait_until(all_in_and_done, 60)
            status = service.status()
            burst = status.sources["burst"]
            assert burst.received == 50
            assert burst.processed + burst.dropped + burst.rejected == burst.received
            assert burst.dropped > 0 and burst.processed >= 2
            assert status.sources["steady"].processed >= 1  # not starved by the burst
            assert status.sources["burst"].last_seq == burst.processed - 1  # every processed frame published, in order
        finally:
            client.close()


def _busy(service: TraversabilityService) -> bool:
    status = service.status()
    return any(s.processed + s.dropped + s.rejected < s.received for s in status.sources.values())
