"""The relay's settings: strict, like every configuration, with the flags on top of the file."""

from __future__ import annotations

from pathlib import Path

import pytest
from gcdtrav.schemas.relay import RelaySettings, RelaySettingsError, load_relay_settings


def test_defaults_and_several_cameras(tmp_path: Path) -> None:
    file = tmp_path / "relay.yaml"
    file.write_text(
        "cameras:\n"
        "  - {camera: /camera/front/image_raw, source: r1/front}\n"
        "  - {camera: robot/rear/jpeg, source: r1/rear}\n"
        "  - {camera: camera/left, source: r1/left, ros_layout: bridge}\n"  # not ROS: no leading slash
        "jpeg_quality: 60\n"
    )
    settings = load_relay_settings(file, {"max_side": 640, "stale_after_s": None})
    assert [c.is_ros for c in settings.cameras] == [True, False, False]
    assert (settings.jpeg_quality, settings.max_side, settings.stale_after_s) == (60, 640, 3.0)
    assert (
        settings.forward == ["maps", "maps8", "grid", "preview", "speed_mask", "costmap", "nav2_costmap"]
        and settings.max_side != "auto"
    )
    assert RelaySettings(cameras=[{"camera": "a", "source": "b"}]).max_side == "auto"  # type: ignore[list-item]


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"cameras": []}, "at least 1"),
        ({"cameras": [{"camera": "a", "source": "b"}], "jpeg_quality": 0}, "jpeg_quality"),
        ({"cameras": [{"camera": "a", "source": "b"}], "jpeg_quality": 101}, "jpeg_quality"),
        ({"cameras": [{"camera": "a", "source": "b"}], "max_side": 8}, "below 16"),
        ({"cameras": [{"camera": "a", "source": "b"}], "max_side": "big"}, "max_side"),
        ({"cameras": [{"camera": "a", "source": "b"}], "credit_timeout_s": 0}, "credit_timeout_s"),
        ({"cameras": [{"camera": "a", "source": "r/*"}]}, "literal zenoh key"),
        ({"cameras": [{"camera": "a", "source": "b"}, {"camera": "c", "source": "b"}]}, "named twice: b"),
        ({"cameras": [{"camera": "/t", "source": "b", "ros_layout": "bridge"}]}, "set ros_message_type"),
        ({"cameras": [{"camera": "a", "source": "b"}], "forward": ["patch"]}, "forward"),
        ({"cameras": [{"camera": "a", "source": "b"}], "histroy": 3}, "Extra inputs"),
    ],
)
def test_bad_settings_fail_loudly(data: dict[str, object], message: str, tmp_path: Path) -> None:
    with pytest.raises(RelaySettingsError, match=message):
        load_relay_settings(None, data)


def test_an_unreadable_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(RelaySettingsError, match=r"relay\.yaml: cannot read"):
        load_relay_settings(tmp_path / "relay.yaml")
    (tmp_path / "list.yaml").write_text("- 1\n")
    with pytest.raises(RelaySettingsError, match="expected a mapping"):
        load_relay_settings(tmp_path / "list.yaml")
