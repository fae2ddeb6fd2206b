"""The speed filter as a Nav2 node on rmw_zenoh takes it, over real zenoh on loopback: a camera (rmw_zenoh's
tokens and keys) feeds a grid with a speed layer; a subscriber on the keys Nav2's SpeedFilter would use gets the
mask and its CostmapFilterInfo; a late one gets the latched last ones; when the grid goes stale and when the
service stops (what SIGTERM runs) it gets the safe mask, the floor everywhere."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from zenoh_helpers import connecting_config, listening, wait_until

pytest.importorskip("rosbags")
pytest.importorskip("xxhash")

from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.bus.ros_graph import entity_gid, rmw_attachment
from gcdtrav.service.ros import cdr as ros
from zenoh import ext

from tools.loopback import in_process_service

IMAGE_HASH = "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47"
BASE = "0/camera/front/image_raw/gcdtrav/grid"
MASK_KEY = f"{BASE}/speed_mask/nav_msgs::msg::dds_::OccupancyGrid_/{ros.type_hash(ros.OCCUPANCY_GRID)}"
INFO_KEY = f"{BASE}/speed_filter_info/nav2_msgs::msg::dds_::CostmapFilterInfo_/{ros.type_hash(ros.COSTMAP_FILTER_INFO)}"
LIMIT_KEY = f"{BASE}/speed_limit/nav2_msgs::msg::dds_::SpeedLimit_/{ros.type_hash(ros.SPEED_LIMIT)}"
FLOOR, STALE_S = 0.3, 3.0
# The tiny random model finds everything ambiguous: ramps it never reaches, so a live mask says "no limit" (0)
# and only the safe one holds the floor.
NEVER_SLOW = {"u_full": 0.99, "u_floor": 1.0, "p_below_full": 0.99, "p_below_floor": 1.0, "unknown": "full"}


class Nav2Side:
    """A camera driver and a Nav2 node on rmw_zenoh: the camera's node and publisher tokens; subscribers as
    rmw_zenoh declares a transient-local one (an advanced subscriber that queries late publishers' caches)."""

    def __init__(self, port: int) -> None:
        self.session = zenoh.open(connecting_config(port))
        zid = str(self.session.info.zid())
        self.camera_key = f"0/camera/front/image_raw/sensor_msgs::msg::dds_::Image_/{IMAGE_HASH}"
        self.publisher_token = (
            f"@ros2_lv/0/{zid}/0/1/MP/%/%/camera_driver/%camera%front%image_raw/"
            f"sensor_msgs::msg::dds_::Image_/{IMAGE_HASH}/2::,5:,:,:,,"
        )
        self.tokens = [
            self.session.liveliness().declare_token(f"@ros2_lv/0/{zid}/0/0/NN/%/%/camera_driver"),
            self.session.liveliness().declare_token(self.publisher_token),
        ]
        self.lock = threading.Lock()
        self.frames = 0
        self.received: dict[str, list[bytes]] = {MASK_KEY: [], INFO_KEY: [], LIMIT_KEY: []}
        self.subscribers = [self.subscribe(key, self.received[key]) for key in (MASK_KEY, INFO_KEY)]
        self.subscribers.append(self.session.declare_subscriber(LIMIT_KEY, self._into(self.received[LIMIT_KEY])))

    def _into(self, samples: list[bytes]) -> Any:
        def on_sample(sample: zenoh.Sample) -> None:
            with self.lock:
                samples.append(sample.payload.to_bytes())

        return on_sample

    def subscribe(self, key: str, samples: list[bytes]) -> Any:
        """A reliable, transient-local, keep-last-1 subscription as rmw_zenoh declares it (the SpeedFilter's)."""
        history = ext.HistoryConfig(detect_late_publishers=True, max_samples=1)
        return ext.declare_advanced_subscriber(self.session, key, self._into(samples), history=history)

    def count(self, key: str) -> int:
        with self.lock:
            return len(self.received[key])

    def last(self, key: str, msgtype: str) -> Any:
        with self.lock:
            return ros.typestore().deserialize_cdr(self.received[key][-1], msgtype)

    def send_frame(self, stamp: float) -> None:
        """A new view each time (the triage would reuse an unchanged one's maps and fuse nothing)."""
        from conftest import textured_image
        from ros_images import image_cdr

        self.frames += 1
        image = textured_image(24, 32, seed=self.frames)
        attachment = rmw_attachment(self.frames, 0, entity_gid(self.publisher_token))
        self.session.put(
            self.camera_key, image_cdr(image, "rgb8", stamp=stamp, frame_id="front"), attachment=attachment
        )

    def close(self) -> None:
        for declared in [*self.subscribers, *self.tokens]:
            declared.undeclare()
        self.session.close()


def settings(tmp_path: Path) -> ServiceSettings:
    return ServiceSettings.model_validate(settings_document(tmp_path))


def settings_document(tmp_path: Path) -> dict[str, Any]:
    return {
        "state_dir": str(tmp_path),
        "instance": "speed",
        "max_frame_age_s": None,
        "inputs": [],
        "ros_inputs": [{"key": "0/**/sensor_msgs::msg::dds_::Image_/*"}],
        "ros_output": {"enabled": True, "preview": "none"},
        "grids": [
            {
                "source": "camera/front/image_raw",
                "intrinsics": {"fx": 30, "fy": 30, "cx": 16, "cy": 12, "width": 32, "height": 24},
                "mount": {"z": 1.0, "pitch": 0.6},
                "size_m": 6.0,
                "resolution_m": 0.5,
                "speed": {"floor": FLOOR, "rate_hz": 10.0, "stale_s": STALE_S, **NEVER_SLOW},
            }
        ],
    }


def graph_tokens(session: zenoh.Session, prefix: str) -> list[str]:
    """The liveliness tokens under ``prefix`` (an entity's zid) alive now."""
    return [str(reply.ok.key_expr) for reply in session.liveliness().get(prefix + "**") if reply.ok is not None]


def is_safe(mask: Any) -> bool:
    return bool((np.asarray(mask.data) == round(FLOOR * 100)).all())


def test_nav2_gets_mask_and_info_late_too_and_the_safe_mask_when_stale_and_at_stop(
    tiny_backend: Any, tmp_path: Path
) -> None:
    with in_process_service(tiny_backend, settings(tmp_path)) as (service, port):
        nav2 = Nav2Side(port)
        try:
            assert service.ros_graph is not None
            ours = f"@ros2_lv/0/{service.ros_graph.zid}/"
            # the service answers the camera's publisher token with its subscription token: it takes frames
            assert wait_until(lambda: any("/MS/" in token for token in graph_tokens(nav2.session, ours)), 60)
            nav2.send_frame(1_700_000_000.0)
            assert wait_until(lambda: nav2.count(MASK_KEY) and nav2.count(INFO_KEY) and nav2.count(LIMIT_KEY), 30)

            info = nav2.last(INFO_KEY, ros.COSTMAP_FILTER_INFO)
            assert (info.type, info.base, info.multiplier) == (1, 0.0, 1.0)
            assert info.filter_mask_topic == "/camera/front/image_raw/gcdtrav/grid/speed_mask"
            mask = nav2.last(MASK_KEY, ros.OCCUPANCY_GRID)
            data = np.asarray(mask.data)
            assert (mask.info.width, mask.info.height, mask.info.resolution) == (12, 12, 0.5)
            assert mask.header.frame_id == info.header.frame_id == "base_link"
            assert data.min() >= 0 and data.max() <= 100  # never -1: Nav2 reads it as an error, keeps the old limit
            assert (data == 0).all() and not is_safe(mask)  # a live mask: no limit anywhere (NEVER_SLOW)
            limit = nav2.last(LIMIT_KEY, ros.SPEED_LIMIT)
            assert limit.percentage and (limit.speed_limit == 0.0 or 1.0 <= limit.speed_limit <= 100.0)

            # the publishers are in the graph with a map's QoS (reliable, transient local, keep-last 1)
            tokens = graph_tokens(nav2.session, ours)
            for topic, dds_type in (("speed_mask", "nav_msgs::msg::dds_::OccupancyGrid_"),
                                    ("speed_filter_info", "nav2_msgs::msg::dds_::CostmapFilterInfo_")):  # fmt: skip
                assert any(f"%gcdtrav%grid%{topic}/{dds_type}/" in t and t.endswith("/:1:,1:,:,:,,") for t in tokens)
            assert any("%speed_limit/nav2_msgs::msg::dds_::SpeedLimit_/" in t and t.startswith(ours) for t in tokens)

            # a second frame: a new mask (rate 10 Hz), the same info not put again
            time.sleep(0.15)
            masks = nav2.count(MASK_KEY)
            nav2.send_frame(1_700_000_000.2)
            assert wait_until(lambda: service.status().grids[0].fused == 2, 30)
            assert wait_until(lambda: nav2.count(MASK_KEY) > masks, 30)
            assert nav2.count(INFO_KEY) == 1

            # a Nav2 node starting late gets the latched last info and mask from the publishers' caches
            late: dict[str, list[bytes]] = {MASK_KEY: [], INFO_KEY: []}
            late_subscribers = [nav2.subscribe(key, late[key]) for key in late]
            assert wait_until(lambda: late[MASK_KEY] and late[INFO_KEY], 30)
            with nav2.lock:
                assert late[INFO_KEY][0] == nav2.received[INFO_KEY][-1]
                assert late[MASK_KEY][0] == nav2.received[MASK_KEY][-1]

            # a third frame, whose mask starts the stale_s below afresh (the waits above may take seconds on a
            # loaded machine: the second frame's mask could already be stale)
            time.sleep(0.15)  # past the 10 Hz rate's period
            masks = nav2.count(MASK_KEY)
            nav2.send_frame(1_700_000_000.3)
            assert wait_until(lambda: service.status().grids[0].fused == 3, 30)
            assert wait_until(lambda: nav2.count(MASK_KEY) > masks, 30)
            status = service.status().grids[0]
            assert status.speed_safe is False and status.speed_ago_s is not None

            # no frame for stale_s: the safe mask (the floor everywhere), once, and the status says so
            masks = nav2.count(MASK_KEY)
            assert wait_until(lambda: nav2.count(MASK_KEY) > masks, STALE_S + 10)
            assert is_safe(nav2.last(MASK_KEY, ros.OCCUPANCY_GRID))
            assert nav2.last(LIMIT_KEY, ros.SPEED_LIMIT).speed_limit == FLOOR * 100
            assert service.status().grids[0].speed_safe is True
            time.sleep(STALE_S)
            assert nav2.count(MASK_KEY) == masks + 1
            for subscriber in late_subscribers:
                subscriber.undeclare()

            # a fresh frame replaces it at once; the service stops (SIGTERM's drain): the safe mask again
            nav2.send_frame(1_700_000_000.4)
            assert wait_until(lambda: service.status().grids[0].speed_safe is False, 30)
            assert wait_until(lambda: nav2.count(MASK_KEY) > masks + 1, 30)
            masks = nav2.count(MASK_KEY)
            service.stop()
            assert wait_until(lambda: nav2.count(MASK_KEY) > masks, 30)
            assert is_safe(nav2.last(MASK_KEY, ros.OCCUPANCY_GRID))
        finally:
            nav2.close()


def test_the_nav2_example_feeds_its_speed_filter_from_gcdtravs_topics() -> None:
    """examples/nav2: the SpeedFilter's filter_info_topic is the info topic the example service publishes, and
    that info names the mask topic the service publishes the mask on."""
    import yaml
    from gcdtrav.schemas.settings import load_settings

    root = Path(__file__).resolve().parents[3] / "examples" / "nav2"
    service = load_settings(root / "gcdtrav.yaml", environ={})
    speed = service.grids[0].speed
    assert speed is not None and speed.lead_m > 0
    costmap = yaml.safe_load((root / "nav2_costmap.yaml").read_text())["local_costmap"]["local_costmap"]
    parameters = costmap["ros__parameters"]
    (name,) = parameters["filters"]
    speed_filter = parameters[name]
    assert speed_filter["plugin"] == "nav2_costmap_2d::SpeedFilter"
    camera = "/" + service.grids[0].source
    names = service.ros_output
    assert speed_filter["filter_info_topic"] == ros.output_topic(names.speed_filter_info_topic, camera)
    assert parameters["global_frame"] == service.grids[0].tf.odom_frame


def test_sigterm_to_gcdtrav_serve_leaves_nav2_the_safe_mask(tiny_model_dir: Path, tmp_path: Path) -> None:
    """The real process: `gcdtrav serve` with a speed grid, frames streaming, SIGTERM: it exits 0 and the last
    mask and SpeedLimit a Nav2 node holds are the floor."""
    import os
    import signal
    import subprocess

    import yaml
    from zenoh_helpers import free_port, serve_args

    document = settings_document(tmp_path) | {"max_sources": 4}
    document.pop("instance")
    path = tmp_path / "speed.yaml"
    path.write_text(yaml.safe_dump(document))
    port = free_port()
    args = serve_args(tiny_model_dir, "-l", f"tcp/127.0.0.1:{port}", "--settings", str(path), "--precision", "fp32")
    env = {**os.environ, "GCDTRAV_SHUTDOWN_GRACE_S": "5"}
    process = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    nav2 = None
    try:
        assert wait_until(lambda: listening(port), 60), "gcdtrav serve did not start"
        nav2 = Nav2Side(port)
        sent = [0.0]

        def live_mask() -> bool:  # frames until a mask that is not the safe one has come
            sent[0] += 0.2
            nav2.send_frame(1_700_000_000.0 + sent[0])
            time.sleep(0.2)
            return nav2.count(MASK_KEY) > 0 and not is_safe(nav2.last(MASK_KEY, ros.OCCUPANCY_GRID))

        if not wait_until(live_mask, 90):
            process.kill()
            pytest.fail(f"no live mask; gcdtrav serve said: {process.communicate()[0][-3000:]}")
        masks = nav2.count(MASK_KEY)
        process.send_signal(signal.SIGTERM)
        output, _ = process.communicate(timeout=30)
        assert process.returncode == 0, output[-2000:]
        assert wait_until(lambda: nav2.count(MASK_KEY) > masks, 30)
        assert is_safe(nav2.last(MASK_KEY, ros.OCCUPANCY_GRID))
        assert nav2.last(LIMIT_KEY, ros.SPEED_LIMIT).speed_limit == FLOOR * 100
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
        if nav2 is not None:
            nav2.close()
