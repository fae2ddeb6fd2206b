"""The ROS 2 node's parameters and names, without rclpy: parameters to relay settings, CameraInfo topics, and
the launch file (launch_ros is not installable here: checked as Python and against the node's parameters)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
from gcdtrav.client.relay.ros_parameters import PARAMETERS, camera_info_topic, settings_overrides
from gcdtrav.schemas.relay import RelaySettings, RelaySettingsError, load_relay_settings

LAUNCH = Path(__file__).resolve().parents[2] / "examples" / "ros2" / "relay.launch.py"


@pytest.mark.parametrize(
    ("image", "info"),
    [
        ("/camera/front/image_raw", "/camera/front/camera_info"),
        ("/camera/front/image_raw/compressed", "/camera/front/camera_info"),  # a transport's subtopic
        ("/image_raw", "/camera_info"),
        ("front/image_raw", "front/camera_info"),  # relative: resolved in the node's namespace
        ("/compressed", "/camera_info"),  # a topic named like a transport, not under one
    ],
)
def test_camera_info_beside_the_image(image: str, info: str) -> None:
    assert camera_info_topic(image) == info


def test_one_camera_from_parameters() -> None:
    overrides = settings_overrides({"camera": "/camera/image_raw", "source": "r1/front", "jpeg_quality": 60})
    settings = RelaySettings.model_validate(overrides)
    assert [(c.camera, c.source, c.camera_info_key) for c in settings.cameras] == [
        ("/camera/image_raw", "r1/front", None)
    ]
    assert settings.jpeg_quality == 60 and settings.odometry is None


def test_many_cameras_and_odometry_from_parameters() -> None:
    overrides = settings_overrides(
        {
            "camera": ["front/image_raw", "rear/image_raw/compressed"],
            "source": ["r1/front", "r1/rear"],
            "camera_info_key": ["robot/r1/front/camera_info", ""],
            "odometry_key": "robot/r1/pose",
        }
    )
    settings = RelaySettings.model_validate(overrides)
    assert [c.camera_info_key for c in settings.cameras] == ["robot/r1/front/camera_info", None]
    assert settings.odometry is not None and settings.odometry.topic == "/odom" and settings.odometry.max_rate_hz == 10


def test_parameters_override_the_yaml(tmp_path: Path) -> None:
    file = tmp_path / "relay.yaml"
    file.write_text("cameras: [{camera: /a, source: a}]\njpeg_quality: 90\nstale_after_s: 2\n")
    settings = load_relay_settings(file, settings_overrides({"jpeg_quality": 50}))
    assert settings.jpeg_quality == 50 and settings.stale_after_s == 2 and settings.cameras[0].camera == "/a"


@pytest.mark.parametrize(
    "parameters",
    [
        {"camera": ["/a", "/b"], "source": "a"},
        {"camera": ["/a"], "source": ["a"], "camera_info_key": ["k", "l"]},
        {"source": "a"},
    ],
)
def test_unpaired_cameras_are_refused(parameters: dict[str, object]) -> None:
    with pytest.raises(ValueError, match=r"camera, .* source"):
        settings_overrides(parameters)


def test_an_odometry_key_must_be_literal() -> None:
    with pytest.raises(RelaySettingsError, match="odometry key"):
        load_relay_settings(None, settings_overrides({"camera": "/a", "source": "a", "odometry_key": "robot/*"}))


def test_the_launch_file_is_python_and_names_only_the_nodes_parameters() -> None:
    tree = ast.parse(LAUNCH.read_text(), str(LAUNCH))
    node = next(
        call
        for call in ast.walk(tree)
        if isinstance(call, ast.Call) and isinstance(call.func, ast.Name) and call.func.id == "Node"
    )
    keywords = {keyword.arg: keyword.value for keyword in node.keywords}
    assert ast.literal_eval(keywords["executable"]) == "gcdtrav"
    assert "package" not in keywords  # a console script on PATH, not a ROS package
    parameters = keywords["parameters"]
    assert isinstance(parameters, ast.List) and isinstance(parameters.elts[0], ast.Dict)
    given = {
        ast.literal_eval(key): value
        for key, value in zip(parameters.elts[0].keys, parameters.elts[0].values, strict=True)
        if key is not None
    }
    assert set(given) - {"use_sim_time"} <= set(PARAMETERS)
    literal = {name: ast.literal_eval(value) for name, value in given.items() if name != "use_sim_time"}
    settings = RelaySettings.model_validate(settings_overrides(literal))
    assert [c.source for c in settings.cameras] == ["r1/front", "r1/rear"]


def test_the_base_install_stays_ros_free() -> None:
    """The zenoh relay imports no rclpy; --ros without it says what to install, exit 1, no traceback."""
    import subprocess
    import sys

    code = (
        "import sys; sys.modules['rclpy'] = None\n"
        "import gcdtrav.client.relay.relay, gcdtrav.client.relay.ros_parameters, gcdtrav.client.commands.relay\n"
        "from gcdtrav.service.commands.cli import main\n"
        "sys.exit(main(['relay', '--ros', '--ros-args', '-p', 'camera:=/a', '-p', 'source:=a']))\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert result.returncode == 1, result.stderr
    assert "gcdtrav relay --ros: needs ROS 2's rclpy" in result.stderr and "Traceback" not in result.stderr


def test_the_guard_of_a_robot_whose_frames_go_straight_to_the_service_from_parameters() -> None:
    """frames:=false for one camera or each, the safe mask's settings, odometry read without a key to send it to."""
    overrides = settings_overrides(
        {
            "camera": ["/a/image_raw", "/b/image_raw"],
            "source": ["r1/a", "r1/b"],
            "frames": False,
            "odometry_topic": "/odom",
            "safe_after_s": 1.5,
            "safe_floor": 0.2,
            "max_speed_m_s": 2.0,
        }
    )
    settings = RelaySettings.model_validate(overrides)
    assert [camera.frames for camera in settings.cameras] == [False, False]
    assert settings.odometry is not None and settings.odometry.key is None and settings.odometry.topic == "/odom"
    assert (settings.safe_mask.after_s, settings.safe_mask.floor, settings.safe_mask.max_speed_m_s) == (1.5, 0.2, 2.0)
    each = settings_overrides({"camera": ["/a", "/b"], "source": ["a", "b"], "frames": [True, False]})
    assert [camera["frames"] for camera in each["cameras"]] == [True, False]  # type: ignore[index]
    with pytest.raises(ValueError, match="3 frames"):
        settings_overrides({"camera": ["/a", "/b"], "source": ["a", "b"], "frames": [True, False, True]})
