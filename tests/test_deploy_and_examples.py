"""The shipped configs parse, and the examples run against a live service."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import pytest
import yaml
import zenoh
from conftest import textured_image

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"


def run_example(script: str, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, str(ROOT / "examples" / script), *args], capture_output=True, text=True, timeout=120
    )


@pytest.mark.parametrize("name", ["zenoh-router.json5", "service-zenoh.json5", "access-control.json5", "tls.json5"])
def test_zenoh_configs_parse(name: str) -> None:
    zenoh.Config.from_file(ROOT / "deploy" / name)


def test_service_settings_example_is_valid() -> None:
    from gcdtrav.schemas.settings import load_settings

    settings = load_settings(ROOT / "deploy" / "service.yaml", environ={})
    assert settings.prefix == "gcdtrav" and settings.inputs == ["gcdtrav/in/**"]


def test_service_yaml_lists_every_setting() -> None:
    """The README says deploy/service.yaml lists every setting (it lacked max_frame_age_s): each field of
    ServiceSettings is a key there, or a commented one for those configured per camera; the fields of the
    nested sections it sets are keys under them."""
    import re

    import yaml
    from gcdtrav.schemas.settings import ServiceSettings

    text = (ROOT / "deploy" / "service.yaml").read_text("utf-8")
    listed = set(re.findall(r"^#? ?([a-z_]+):", text, re.MULTILINE))
    assert set(ServiceSettings.model_fields) - listed == set()
    values = yaml.safe_load(text)
    for section, model in ServiceSettings.model_fields.items():
        if isinstance(values.get(section), dict):
            nested = model.annotation.model_fields  # type: ignore[union-attr]
            assert set(nested) - set(values[section]) == set(), section


def test_the_planning_example_writes_its_figure_where_it_runs(tmp_path: Path) -> None:
    """It wrote into the checkout's docs/ by default; now into the working directory, or --out."""
    pytest.importorskip("matplotlib")
    shipped = ROOT / "docs" / "ambiguity-aware-planning.png"
    before = shipped.stat().st_mtime_ns
    script = str(ROOT / "examples" / "ambiguity_aware_planning.py")
    ran = subprocess.run([sys.executable, script], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert ran.returncode == 0, ran.stderr
    assert (tmp_path / "ambiguity-aware-planning.png").stat().st_size > 10_000
    elsewhere = run_example("ambiguity_aware_planning.py", "--out", str(tmp_path / "plots" / "p.png"))
    assert elsewhere.returncode == 0 and (tmp_path / "plots" / "p.png").exists()
    assert shipped.stat().st_mtime_ns == before


def test_example_anchor_set_is_valid() -> None:
    from gcdtrav.schemas.anchors import AnchorSet

    assert len(AnchorSet.load(ROOT / "examples" / "anchors" / "puddles.yaml")) == 8


def test_robot_planner_and_operator_examples(tiny_backend, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    pytest.importorskip("torch")
    from gcdtrav.schemas.settings import ServiceSettings

    from tools.loopback import in_process_service

    folder = tmp_path / "images"
    folder.mkdir()
    for index in range(3):
        cv2.imwrite(str(folder / f"{index:03d}.jpg"), textured_image(60, 80, seed=index))
    settings = ServiceSettings(state_dir=tmp_path / "state", instance="examples")
    with in_process_service(tiny_backend, settings) as (service, port):
        flags = ["-e", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting"]
        # No sleep: the service subscribed when it started, and a session knows its peer's subscriptions once
        # open() returns; the example subscribes to its maps before its first image. --wait bounds a failure.
        robot = run_example(
            "robot_stream_folder.py", str(folder), "--source", "r9/cam", "--fps", "4", "--wait", "60", *flags
        )
        assert robot.returncode == 0, robot.stderr
        assert "sent 2: 002.jpg" in robot.stdout and "maps r9/cam seq=" in robot.stdout
        planner = run_example("planner_probe.py", "--source", "r9/cam", "--x", "40", "--y", "30", *flags)
        assert planner.returncode == 0, planner.stderr
        assert "T (mean) =" in planner.stdout and "concrete @ 1.00" in planner.stdout
        missing = run_example("planner_probe.py", "--source", "nobody", "--x", "1", "--y", "1", *flags)
        assert missing.returncode == 1 and "unknown source 'nobody'" in missing.stderr
        puddles = str(ROOT / "examples" / "anchors" / "puddles.yaml")  # the operator's command replaced the script
        command = [sys.executable, "-m", "gcdtrav.service.commands.cli", "anchors", "set", puddles, *flags]
        operator = subprocess.run(command, capture_output=True, text=True, timeout=60)
        assert operator.returncode == 0, operator.stderr
        assert len(service.pipeline.anchors) == 8


@pytest.mark.parametrize("name", ["rmw_zenoh.yaml", "zenoh_bridge.yaml"])
def test_ros_examples_are_valid_settings(name: str) -> None:
    from gcdtrav.schemas.settings import load_settings

    settings = load_settings(ROOT / "examples" / "ros2" / name, environ={})
    assert settings.ros_output.enabled and settings.ros_inputs and settings.inputs == []


def test_bridge_input_without_a_type_is_rejected() -> None:
    from gcdtrav.schemas.settings import SettingsError, load_settings

    with pytest.raises(SettingsError, match="bridge keys carry no type"):
        load_settings(None, {"ros_inputs": [{"key": "cam", "layout": "bridge"}]}, environ={})


def test_grid_example_settings_are_valid() -> None:
    from gcdtrav.schemas.settings import load_settings

    settings = load_settings(ROOT / "examples" / "grid.yaml", environ={})
    assert settings.grids[0].source == "cam" and settings.grids[0].pose_key == "robot/pose"


def test_experience_example_and_the_readme_commands_of_its_section() -> None:
    """examples/experience.yaml loads; every `gcdtrav` line of "Let the robot's driving tune it" parses with
    today's CLI (tests/service/bus/test_experience_e2e.py runs them against a live service)."""
    import shlex

    from gcdtrav.schemas.settings import load_settings
    from gcdtrav.service.commands.cli import build_parser

    settings = load_settings(ROOT / "examples" / "experience.yaml", environ={})
    assert settings.experience.enabled and settings.ask.enabled and settings.experience.cmd_vel == "/cmd_vel"
    readme = (ROOT / "README.md").read_text("utf-8")
    section = readme.split("## Let the robot's driving tune it", 1)[1].split("\n## ", 1)[0]
    lines = [line for line in section.splitlines() if line.startswith("gcdtrav ")]
    commands = {build_parser().parse_args(shlex.split(line, comments=True)[1:]).command for line in lines}
    assert {"serve", "calibration", "anchors", "status", "answer"} <= commands


def test_readme_python_example_runs(tiny_backend, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    """The README's client snippet, copied as it is, against a live service (only the zenoh config swapped
    for a loopback one without multicast)."""
    pytest.importorskip("torch")
    import re

    from gcdtrav.schemas.anchors import AnchorSet, default_anchor_set
    from gcdtrav.schemas.settings import ServiceSettings

    from tools.loopback import in_process_service

    readme = (ROOT / "README.md").read_text()
    snippet = re.search(r"```python\n(.*?)```", readme, re.S)
    assert snippet is not None
    with in_process_service(tiny_backend, ServiceSettings(state_dir=tmp_path, instance="readme")) as (service, port):
        code = snippet.group(1).replace(
            'zenoh_config(mode="peer")',
            f'zenoh_config(mode="peer", connect=["tcp/127.0.0.1:{port}"], multicast_scouting=False)',
        )
        assert code != snippet.group(1)
        result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
        assert result.returncode == 0, result.stderr
        assert "'r1/front': SourceStatus(received=1, processed=1" in result.stdout
        # the snippet swapped in the whole set plus a puddle, then rolled back to the whole set
        paper = default_anchor_set().model_dump()
        extended = sorted([*paper["anchors"], {"concept": "puddle", "position": 0.05}], key=lambda a: a["position"])
        assert AnchorSet.parse({**paper, "anchors": extended}).version in result.stdout
        assert service.pipeline.anchors == default_anchor_set()


def test_container_health_check_finds_its_instance(tiny_backend, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    pytest.importorskip("torch")
    from gcdtrav.schemas.settings import ServiceSettings

    from tools.loopback import in_process_service

    def health(*args: str) -> subprocess.CompletedProcess[str]:
        command = [sys.executable, "-m", "gcdtrav.client.commands.health", "--timeout", "10", *args]
        return subprocess.run(command, capture_output=True, text=True, timeout=60)

    settings = ServiceSettings(state_dir=tmp_path / "state")  # the default name: {hostname}-{pid}
    with in_process_service(tiny_backend, settings) as (_, port):
        flags = ["-m", "client", "-e", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting"]
        healthy = health(*flags)
        assert healthy.returncode == 0 and healthy.stdout.strip() == "healthy", healthy.stderr
        other = health(*flags, "--instance", "another-box")
        assert other.returncode == 1
        assert (
            other.stderr.strip()
            == f"unhealthy: instance another-box did not answer (answered: ['{settings.instance}'])"
        )
    gone = health("-m", "peer", "-e", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting")
    assert gone.returncode == 1 and gone.stderr.startswith("unhealthy:")


def test_planner_path_calls_a_cell_mostly_one_anchor_only_when_it_is() -> None:
    import runpy

    from gcdtrav.schemas.messages import AnchorPoint, ContextDistribution

    ground_of = runpy.run_path(str(ROOT / "examples" / "planner_path.py"))["ground_of"]
    concepts = [f"c{k}" for k in range(11)] + ["water"]
    spread = [0.08] * 11 + [0.12]  # the run's cell: 'water' on top at a few per cent
    cell = ContextDistribution.model_construct(
        anchors=[AnchorPoint(concept=c, position=k / 12, width=0.05) for k, c in enumerate(concepts)],
        weights=spread,
        top_anchors=[11, 0, 1],
    )
    assert ground_of(cell) == "mixed: 'water' 12%, 'c0' 8%, 'c1' 8%"
    dominant = cell.model_copy(update={"weights": [0.02] * 11 + [0.78]})
    assert ground_of(dominant) == "mostly 'water' (78%)"


# nav2_collision_monitor's parameter names as its sources read them (navigation2 main, 0148fcb3, read
# 2026-11-28): the node's (collision_monitor_node.cpp getParameters), each source's (source.cpp
# getCommonParameters; costmap.cpp getParameters), each polygon's (polygon.cpp getCommonParameters; circle.cpp).
COLLISION_MONITOR_NODE = {
    "base_frame_id", "odom_frame_id", "cmd_vel_in_topic", "cmd_vel_out_topic", "state_topic", "transform_tolerance",
    "source_timeout", "base_shift_correction", "stop_pub_timeout", "collision_points_marker_3d", "polygons",
    "observation_sources", "use_sim_time",
}  # fmt: skip
COSTMAP_SOURCE = {"type", "topic", "enabled", "source_timeout", "exclusion_zones", "cost_threshold",
                  "treat_unknown_as_obstacle"}  # fmt: skip
CIRCLE_POLYGON = {"type", "radius", "action_type", "enabled", "min_points", "slowdown_ratio", "linear_limit",
                  "angular_limit", "time_before_collision", "simulation_time_step", "visualize",
                  "polygon_pub_topic", "polygon_sub_topic", "footprint_topic"}  # fmt: skip


def test_the_collision_monitor_example_names_only_nav2s_parameters_and_reads_gcdtravs_costmap() -> None:
    from gcdtrav.schemas.settings import ServiceSettings

    example = yaml.safe_load((EXAMPLES / "nav2" / "collision_monitor.yaml").read_text())
    parameters = example["collision_monitor"]["ros__parameters"]
    sources, polygons = parameters["observation_sources"], parameters["polygons"]
    assert set(parameters) - set(sources) - set(polygons) <= COLLISION_MONITOR_NODE
    for name in sources:
        assert set(parameters[name]) <= COSTMAP_SOURCE and parameters[name]["type"] == "costmap"
    for name in polygons:
        assert set(parameters[name]) <= CIRCLE_POLYGON and parameters[name]["type"] == "circle"
        assert parameters[name]["action_type"] in ("stop", "slowdown", "limit", "approach")
    gcdtrav = parameters["gcdtrav"]
    # the topic the service publishes the nav2_msgs/Costmap on, for the camera of examples/nav2/gcdtrav.yaml
    template = ServiceSettings().ros_output.nav2_costmap_topic
    assert gcdtrav["topic"] == "/" + template.replace("{topic}", "camera/front/image_raw")
    assert 0 <= gcdtrav["cost_threshold"] <= 255 and gcdtrav["treat_unknown_as_obstacle"] is False
    assert gcdtrav["source_timeout"] > 0  # 0 would never stop on stale data (sourceValid skips the check)
