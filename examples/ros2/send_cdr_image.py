"""Play a ROS 2 camera: publish one sensor_msgs/Image as CDR on Zenoh, print what gcdtrav sends back.

    gcdtrav serve --settings examples/ros2/rmw_zenoh.yaml -l tcp/127.0.0.1:7447      # terminal 1
    python examples/ros2/send_cdr_image.py image.jpg -e tcp/127.0.0.1:7447           # terminal 2
    python examples/ros2/send_cdr_image.py image.jpg --distro humble -e ...           # a Humble robot
    python examples/ros2/send_cdr_image.py image.jpg --layout bridge -e ...           # a bridge robot

In the rmw_zenoh layout the script behaves as an rmw_zenoh camera driver: it declares its node and
publisher liveliness tokens, waits (as image_transport does) until the graph holds a subscription for
its topic, sends one frame with rmw_zenoh's attachment, and prints the service's graph tokens and the
keys of its outputs. Needs rosbags and xxhash (installed with gcdtrav[service]); no ROS installation.
"""

from __future__ import annotations

import argparse
import threading
import time
from pathlib import Path

import numpy as np
import zenoh
from gcdtrav.client import Maps, TraversabilityClient, add_zenoh_arguments, zenoh_config_from_args
from gcdtrav.schemas.images import decode_image
from gcdtrav.service.bus.ros_graph import entity_gid, rmw_attachment
from gcdtrav.service.ros import cdr as ros


def image_payload(rgb: np.ndarray, stamp: float, frame_id: str) -> bytes:
    message = ros.typestore().types[ros.IMAGE](
        header=ros.make_header(stamp, frame_id),
        height=rgb.shape[0],
        width=rgb.shape[1],
        encoding="rgb8",
        is_bigendian=0,
        step=rgb.shape[1] * 3,
        data=rgb.ravel(),
    )
    return bytes(ros.typestore().serialize_cdr(message, ros.IMAGE))


class GraphWatch:
    """Every liveliness token of the ROS graph in this domain, live or gone."""

    def __init__(self, session: zenoh.Session, domain: int) -> None:
        self.tokens: dict[str, bool] = {}
        self.changed = threading.Condition()
        self.subscriber = session.liveliness().declare_subscriber(f"@ros2_lv/{domain}/**", self._on, history=True)

    def _on(self, sample: zenoh.Sample) -> None:
        with self.changed:
            self.tokens[str(sample.key_expr)] = sample.kind == zenoh.SampleKind.PUT
            self.changed.notify_all()

    def live(self, kind: str | None = None) -> list[str]:
        with self.changed:
            return sorted(k for k, alive in self.tokens.items() if alive and (kind is None or f"/{kind}/" in k))

    def wait_for(self, predicate, timeout: float) -> bool:  # type: ignore[no-untyped-def]
        with self.changed:
            return self.changed.wait_for(predicate, timeout)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("image", type=Path, help="a JPEG or PNG file, sent as an rgb8 sensor_msgs/Image")
    parser.add_argument("--topic", default="/camera/front/image_raw")
    parser.add_argument("--layout", choices=["rmw_zenoh", "bridge"], default="rmw_zenoh")
    parser.add_argument("--distro", choices=["jazzy", "humble"], default="jazzy", help="the camera's type hashes")
    parser.add_argument("--frame-id", default="front_camera_optical")
    parser.add_argument("--timeout", type=float, default=30.0)
    add_zenoh_arguments(parser)
    args = parser.parse_args()

    rgb = decode_image(args.image.read_bytes())
    stamp = time.time()
    payload = image_payload(rgb, stamp, args.frame_id)
    type_hash = ros.HUMBLE_HASH if args.distro == "humble" else None
    topic = ros.RosTopic(args.topic, ros.IMAGE, args.layout, type_hash=type_hash)
    key = ros.topic_key(topic)
    t_key = ros.topic_key(topic.derived(ros.output_topic("{topic}/gcdtrav/traversability", args.topic), ros.IMAGE))
    got_maps, got_ros = threading.Event(), threading.Event()
    results: dict[str, object] = {}
    outputs: dict[str, bool] = {}  # output key -> carried rmw_zenoh's attachment

    def on_maps(maps: Maps) -> None:
        results["maps"] = maps
        got_maps.set()

    def on_output(sample: zenoh.Sample) -> None:
        outputs[str(sample.key_expr)] = sample.attachment is not None
        if str(sample.key_expr) == t_key:
            results["ros"] = sample.payload.to_bytes()
            got_ros.set()

    with TraversabilityClient(config=zenoh_config_from_args(args)) as client:
        session = client.session
        subscriber = client.subscribe_maps(topic.source, on_maps)
        ros_subscriber = session.declare_subscriber(key.split("/sensor_msgs::")[0] + "/gcdtrav/**", on_output)
        attachment = None
        if args.layout == "rmw_zenoh":
            graph = GraphWatch(session, topic.domain)
            zid = str(session.info.zid())
            hash_chunk = type_hash or ros.type_hash(ros.IMAGE)
            mangled = args.topic.replace("/", "%")
            publisher_token = (
                f"@ros2_lv/0/{zid}/0/1/MP/%/%/camera_driver/{mangled}/{ros.dds_type_name(ros.IMAGE)}/"
                f"{hash_chunk}/2::,5:,:,:,,"
            )
            tokens = [
                session.liveliness().declare_token(f"@ros2_lv/0/{zid}/0/0/NN/%/%/camera_driver"),
                session.liveliness().declare_token(publisher_token),
            ]
            subscribed = f"/MS/%/%/gcdtrav/{mangled}/"  # any gcdtrav node subscribed to our topic
            if not graph.wait_for(lambda: any(subscribed in k for k in graph.live("MS")), args.timeout):
                raise SystemExit("no subscription token for the topic: is `gcdtrav serve` running with ROS inputs?")
            attachment = rmw_attachment(1, time.time_ns(), entity_gid(publisher_token))
        time.sleep(0.5)
        session.put(key, payload, attachment=attachment)
        print(
            f"sent    {key}\n        {len(payload)} bytes of CDR, {rgb.shape[1]}x{rgb.shape[0]} rgb8, "
            f"stamp {stamp:.6f}, frame_id {args.frame_id}"
        )
        if not (got_maps.wait(args.timeout) and got_ros.wait(args.timeout)):
            raise SystemExit("no answer: is `gcdtrav serve` running with ROS inputs and ros_output enabled?")
        maps = results["maps"]
        assert isinstance(maps, Maps)
        h = maps.header
        print(
            f"msgpack gcdtrav/out/{topic.source}/maps\n        seq {h.seq}, stamp {h.stamp:.6f}, frame_id "
            f"{h.frame_id}, map {h.map_shape}, T mean {maps.traversability.mean():.4f}, "
            f"U mean {maps.uncertainty.mean():.4f}, anchors {h.anchor_set_version}, {h.inference_ms:.0f} ms"
        )
        image = ros.typestore().deserialize_cdr(results["ros"], ros.IMAGE)
        values = np.frombuffer(bytes(image.data), dtype="<f4").reshape(image.height, image.width)
        stamp_out = image.header.stamp.sec + image.header.stamp.nanosec * 1e-9
        print(
            f"ROS     {t_key}\n        sensor_msgs/msg/Image {image.encoding} {image.width}x{image.height}, "
            f"stamp {stamp_out:.6f}, frame_id {image.header.frame_id}, T mean {values.mean():.4f}"
        )
        time.sleep(1.0)  # the other outputs of the frame
        print("outputs (key, rmw_zenoh attachment):")
        for output_key, attached in sorted(outputs.items()):
            print(f"        {output_key}  {'attachment' if attached else 'no attachment'}")
        if args.layout == "rmw_zenoh":
            print("graph tokens of the service:")
            for token in graph.live():
                if f"/{zid}/" not in token:
                    print(f"        {token}")
            for token in tokens:
                token.undeclare()
            graph.subscriber.undeclare()
        subscriber.undeclare()
        ros_subscriber.undeclare()


if __name__ == "__main__":
    main()
