"""A frame flows forward: the worker fuses the ground grid, the outputs only encode, the sink only puts, and
the credits hear of maps that went out, through one hand-off."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
from fakes import assembled, png_frame, processed
from gcdtrav.schemas.messages import GridMessage
from gcdtrav.schemas.settings import ReuseSettings, ServiceSettings
from gcdtrav.service.runtime.grids import GridOutputs
from gcdtrav.service.runtime.outputs import FramePublisher, Output, OutputBuilder
from gcdtrav.service.runtime.triage.change import Glance
from gcdtrav.service.runtime.triage.reuse import Republished

LOG = __import__("logging").getLogger("test")
GRID = {
    "source": "cam",
    "intrinsics": {"fx": 40, "fy": 40, "cx": 32, "cy": 24, "width": 64, "height": 48},
    "mount": {"z": 1.0, "pitch": 0.5},
    "size_m": 6.0,
    "resolution_m": 0.5,
}


def settings() -> ServiceSettings:
    return ServiceSettings.model_validate({"grids": [GRID], "preview": False})


class Sink:
    """Records what is put; refuses once closed, as the bus does."""

    def __init__(self, compact: bool = False) -> None:
        self.put_by_source: dict[str, list[Output]] = {}
        self.closed, self.compact, self.asked = False, compact, 0

    def wants_compact(self, source: str) -> bool:
        self.asked += 1
        return self.compact

    def put(self, source: str, outputs: list[Output]) -> bool:
        if self.closed:
            return False
        self.put_by_source[source] = outputs
        return True


def test_the_worker_fuses_the_grid_of_a_camera_and_hands_the_fused_grid_on() -> None:
    config = settings().model_copy(update={"reuse": ReuseSettings(enabled=False)})
    runtime, sink, _ = assembled(config)
    grids, queue, worker = runtime.grids, runtime.queue, runtime.worker
    assert grids is not None
    worker.start()
    try:
        queue.put("cam", png_frame("cam"))
        queue.put("other", png_frame("other"))
        deadline = time.monotonic() + 60  # a failure's bound
        while len(sink.put_by_source) < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        worker.stop(time.monotonic() + 5)
    by_source = {source: {output.key: output for output in outputs} for source, outputs in sink.put_by_source}
    assert sink.keys.grid("other") not in by_source["other"]  # no grid fed by that camera
    fused = GridMessage.unpack(by_source["cam"][sink.keys.grid("cam")].payload)
    assert fused.header.seq == 0 and grids.sources["cam"].seq == 0
    maps = next(maps for maps in sink.maps() if maps.header.source == "cam")
    assert fused.header.anchor_set_version == maps.header.anchor_set_version


def test_the_outputs_only_encode_the_grid_the_worker_fused() -> None:
    config = settings()
    grids = GridOutputs(config.grids, 13, "test", config.risk)
    done = processed("cam")
    maps = done.result.maps
    done = replace(done, grid=grids.fuse("cam", done.record, maps.weights, maps.match))
    builder = OutputBuilder(config, "fake")
    first, again = builder.build(done), builder.build(done)
    grid_of = {o.key: o.payload for o in first}["gcdtrav/out/cam/grid"]
    assert grid_of == {o.key: o.payload for o in again}["gcdtrav/out/cam/grid"]  # building fused nothing more
    assert GridMessage.unpack(grid_of).header.seq == 0 and grids.sources["cam"].seq == 0
    unfused = {o.key for o in builder.build(replace(done, grid=None))}
    assert "gcdtrav/out/cam/grid" not in unfused and "gcdtrav/out/cam/maps" in unfused


def test_the_hand_off_out_puts_then_tells_the_credits_and_refuses_once_closed() -> None:
    sink, told = Sink(compact=True), []
    publish = FramePublisher(OutputBuilder(ServiceSettings(preview=False), "fake"), sink, lambda *a: told.append(a))
    done = processed("r1/front")
    assert publish(done)
    keys = {o.key for o in sink.put_by_source["r1/front"]}
    assert keys == {"gcdtrav/out/r1/front/maps", "gcdtrav/out/r1/front/maps8"} and sink.asked == 1
    assert told == [("r1/front", done.image.stamp)]
    sink.closed = True
    assert not publish(done) and len(told) == 1  # nothing went out: the credits are not told


def test_an_unchanged_frame_leaves_through_the_same_hand_off_and_tells_the_credits_its_stamp() -> None:
    sink, told = Sink(), []
    publish = FramePublisher(OutputBuilder(ServiceSettings(preview=False), "fake"), sink, lambda *a: told.append(a))
    later = png_frame("r1/front")
    seen = Glance(np.zeros((4, 4), np.float32), 99.5, "cam")
    assert publish.republish(later, seen) is Republished.NOT_PUT and told == []  # no maps of the source kept yet
    assert publish(processed("r1/front"))
    assert publish.republish(later, seen) is Republished.PUT and told[-1] == ("r1/front", 99.5)
    assert [o.key for o in sink.put_by_source["r1/front"]] == ["gcdtrav/out/r1/front/maps"]
    answered = sink.put_by_source["r1/front"]
    assert publish.republish(later, seen, fits=lambda: False) is Republished.SUPERSEDED  # nothing put, not told
    assert sink.put_by_source["r1/front"] is answered and len(told) == 2
    publish.forget("r1/front")
    assert publish.republish(later, seen) is Republished.NOT_PUT
