"""A Lichtblick (and Foxglove) layout for the sources a service has: one tab per source with its camera, T and
U, the 3D panel (grid, a risk layer, the robot, its camera's frustum), the probed distribution, the grid
layers' pictures, the log, the Parameters panel and the status. `gcdtrav view --layout FILE` writes it;
examples/foxglove/gcdtrav-layout.json is the one-source layout it generalises."""

from __future__ import annotations

import re
from typing import Any

from gcdtrav.client.view.grid_layers import COSTMAP, LAYERS
from gcdtrav.schemas.messages import ServiceStatus

Mosaic = str | dict[str, Any]  # a panel id, or a split of two mosaics
RISK_LAYER = "cvar"  # the layer the 3D panel shows at first; the others are one click away
PICTURE_LAYERS = ("cvar", "p_below", "match", COSTMAP)  # the grid pictures a tab shows


def service_sources(statuses: list[ServiceStatus], extra: list[str] | None = None) -> list[str]:
    """Every source any instance tracks, and ``extra`` (e.g. grids published under their own name), sorted."""
    found = {source for status in statuses for source in status.sources} | set(extra or [])
    return sorted(found)


def split(direction: str, first: Mosaic, second: Mosaic, percent: float = 50) -> dict[str, Any]:
    return {"direction": direction, "first": first, "second": second, "splitPercentage": percent}


def panel_id(kind: str, source: str, name: str) -> str:
    """Lichtblick's '{PanelType}!{id}', unique per source."""
    return f"{kind}!gcdtrav-{re.sub(r'[^A-Za-z0-9_-]', '-', source)}-{name}"


def source_tab(source: str, prefix: str, configs: dict[str, Any]) -> dict[str, Any]:
    """The tab of one source: its panels' configs go into ``configs``; returns the tab."""
    topic = f"/{prefix}/{source}"

    def image(name: str, image_topic: str, calibration: str | None = None) -> str:
        identifier = panel_id("Image", source, name)
        mode: dict[str, Any] = {"imageTopic": image_topic}
        if calibration:
            mode["calibrationTopic"] = calibration
        configs[identifier] = {"imageMode": mode}
        return identifier

    three_d = panel_id("3D", source, "grid")
    grid_topics: dict[str, Any] = {f"{topic}/grid/{name}": {"visible": False, "colorMode": "rgba-fields"}
                                   for name, _ in LAYERS}  # fmt: skip
    grid_topics[f"{topic}/grid/{COSTMAP}"] = {"visible": False, "colorMode": "rgba-fields"}
    grid_topics[f"{topic}/grid/{RISK_LAYER}"]["visible"] = True
    configs[three_d] = {
        "followTf": "base_link",
        "followMode": "follow-position",
        "topics": {
            **grid_topics,
            f"{topic}/grid": {"visible": False, "colorMode": "rgba-fields"},
            f"{topic}/robot": {"visible": True},
            f"{topic}/camera_info": {"visible": True},
        },
        "publish": {"type": "point", "pointTopic": "/clicked_point"},
    }
    log = panel_id("RosOut", source, "log")
    configs[log] = {"searchTerms": [], "minLogLevel": 1, "topicToRender": f"/{prefix}/log"}
    parameters = panel_id("Parameters", source, "anchors")
    configs[parameters] = {}
    status = panel_id("RawMessages", source, "status")
    configs[status] = {"topicPath": f"{topic}/status"}
    questions = panel_id("RawMessages", source, "question")
    configs[questions] = {"topicPath": f"{topic}/question"}
    pictures = [image(f"layer-{name}", f"{topic}/grid/{name}/image") for name in PICTURE_LAYERS]

    images = split(
        "row",
        image("camera", f"{topic}/camera", f"{topic}/camera_info"),
        split("row", image("t", f"{topic}/traversability"), image("u", f"{topic}/uncertainty")),
        33,
    )
    layers = split("row", split("row", pictures[0], pictures[1]), split("row", pictures[2], pictures[3]))
    middle = split("row", three_d, image("distribution", f"{topic}/distribution"), 60)
    left = split("column", images, split("column", middle, layers, 65), 35)
    right = split("column", parameters, split("column", split("column", status, questions), log, 50), 40)
    return {"title": source, "layout": split("row", left, right, 75)}


def layout(sources: list[str], prefix: str = "gcdtrav") -> dict[str, Any]:
    """The layout: a Tab panel with one tab per source (the first active)."""
    if not sources:
        raise ValueError("a layout needs at least one source")
    configs: dict[str, Any] = {}
    tabs = [source_tab(source, prefix, configs) for source in sources]
    configs["Tab!gcdtrav-sources"] = {"activeTabIdx": 0, "tabs": tabs}
    return {
        "configById": configs,
        "globalVariables": {},
        "userNodes": {},
        "playbackConfig": {"speed": 1},
        "layout": "Tab!gcdtrav-sources",
    }
