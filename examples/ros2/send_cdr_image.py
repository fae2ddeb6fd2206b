"""Play a ROS 2 camera: publish one sensor_msgs/Image as CDR on Zenoh, print what gcdtrav sends back.

    gcdtrav serve --settings examples/ros2/rmw_zenoh.yaml -l tcp/127.0.0.1:7447      # terminal 1
    python examples/ros2/send_cdr_image.py image.jpg -e tcp/127.0.0.1:7447           # terminal 2
    python examples/ros2/send_cdr_image.py image.jpg --layout bridge -e ...           # a bridge robot

Needs rosbags (installed with gcdtrav[service]); no ROS installation.
"""

from __future__ import annotations

import argparse
import threading
import time
from pathlib import Path

import numpy as np
from gcdtrav.client import Maps, TraversabilityClient, add_zenoh_arguments, zenoh_config_from_args
from gcdtrav.schemas.images import decode_image
from gcdtrav.service.bus import ros


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("image", type=Path, help="a JPEG or PNG file, sent as an rgb8 sensor_msgs/Image")
    parser.add_argument("--topic", default="/camera/front/image_raw")
    parser.add_argument("--layout", choices=["rmw_zenoh", "bridge"], default="rmw_zenoh")
    parser.add_argument("--frame-id", default="front_camera_optical")
    parser.add_argument("--timeout", type=float, default=30.0)
    add_zenoh_arguments(parser)
    args = parser.parse_args()

    rgb = decode_image(args.image.read_bytes())
    stamp = time.time()
    header = ros.make_header(stamp, args.frame_id)
    message = ros.typestore().types[ros.IMAGE](
        header=header,
        height=rgb.shape[0],
        width=rgb.shape[1],
        encoding="rgb8",
        is_bigendian=0,
        step=rgb.shape[1] * 3,
        data=rgb.ravel(),
    )
    payload = bytes(ros.typestore().serialize_cdr(message, ros.IMAGE))
    topic = ros.RosTopic(args.topic, ros.IMAGE, args.layout)
    key = ros.topic_key(topic)
    t_key = ros.output_key(topic, "gcdtrav/traversability", ros.IMAGE)
    got_maps, got_ros = threading.Event(), threading.Event()
    results: dict[str, object] = {}

    def on_maps(maps: Maps) -> None:
        results["maps"] = maps
        got_maps.set()

    with TraversabilityClient(config=zenoh_config_from_args(args)) as client:
        subscriber = client.subscribe_maps(topic.source, on_maps)
        ros_subscriber = client.session.declare_subscriber(
            t_key, lambda sample: (results.__setitem__("ros", sample.payload.to_bytes()), got_ros.set())
        )
        time.sleep(0.5)
        client.session.put(key, payload)
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
        subscriber.undeclare()
        ros_subscriber.undeclare()


if __name__ == "__main__":
    main()
