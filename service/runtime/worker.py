"""The worker threads: the newest frame of the next source is decoded and inferred, then the engine, the
history, the ground grid's fusion and the outputs follow. No zenoh here: frames come from the latest-only
queue, results leave through ``publish`` (in the service, runtime/outputs.py's ``FramePublisher``).
Whatever a frame raises is counted against that frame and never stops a thread."""

from __future__ import annotations

import logging
import os
import queue
import sys
import threading
import time
from collections.abc import Callable
from typing import Any, TypeVar

from gcdtrav.schemas.inputs import DecodedFrame, RejectedInput, decode_payload
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.backends.cpus import usable_cpus
from gcdtrav.service.pipeline import FrameResult, Pipeline
from gcdtrav.service.ros import cdr as ros_io
from gcdtrav.service.runtime.frames import InferredFrame, PendingFrame, ProcessedFrame
from gcdtrav.service.runtime.grids import FusedGrid, GridOutputs
from gcdtrav.service.runtime.history import FrameHistory, FrameRecord
from gcdtrav.service.runtime.intake.admission import Admission
from gcdtrav.service.runtime.intake.freshness import Dropped, FrameGate, Freshness, check_stamp
from gcdtrav.service.runtime.intake.sources import SourceTracker
from gcdtrav.service.runtime.progress import ProgressMonitor
from gcdtrav.service.runtime.schedule.latest_queue import LatestFrameQueue
from gcdtrav.service.runtime.stats import ServiceStats
from gcdtrav.service.runtime.triage.reuse import Reusable, Triage

log = logging.getLogger("gcdtrav.service")
_R = TypeVar("_R")
# The hand-off out (runtime/outputs.py's FramePublisher): a processed frame's maps kept for reuse, then the
# callback told (the glance's new reference), then the payloads put; False: nothing put (closed).
Publish = Callable[[ProcessedFrame, Callable[[ProcessedFrame], None]], bool]


class FrameWorker:
    def __init__(
        self,
        frames: LatestFrameQueue[PendingFrame],
        pipeline: Pipeline,
        history: FrameHistory,
        stats: ServiceStats,
        sources: SourceTracker,
        settings: ServiceSettings,
        publish: Publish,
        on_taken: Callable[[PendingFrame], None] = lambda pending: None,
        progress: ProgressMonitor | None = None,
        gate: FrameGate | None = None,
        admission: Admission | None = None,
        triage: Triage | None = None,
        grids: GridOutputs | None = None,
    ) -> None:
        self.frames, self.pipeline, self.history, self.stats = frames, pipeline, history, stats
        self.sources, self.settings, self.publish = sources, settings, publish
        self.on_taken = on_taken  # the source's slot is free: its sender may send the next frame (credits)
        self.progress = progress or ProgressMonitor(float("inf"))  # beaten round every loop and after every step
        self.admission = admission  # a new source takes a slot once its frame decodes; None: every source has one
        self.grids = grids  # the ground grids a computed frame is fused into (before its outputs are encoded)
        # stamps, ownership and age before inference and again before publishing
        self.gate = gate or FrameGate(lambda source: True, Freshness.from_settings(settings))
        self.triage = triage  # frames glanced at on their own thread first: unchanged views reuse the last maps
        # With a CPU left over by torch (threads below the CPUs this process may use), a second thread
        # runs the last frame's engine work, encoding and publishing while the next frame is decoded and
        # inferred: +9 % frames/s with 1 torch thread on 2 cores (benchmarks/README.md). When torch has every
        # CPU, overlapping only makes both compete (-3 % frames/s, +25 ms latency measured), so one thread
        # does it all. The frame to infer is always taken from the latest-only queue just in time.
        self.overlap_outputs = settings.threads is not None and settings.threads < usable_cpus()
        self._inferred: queue.Queue[InferredFrame | None] = queue.Queue(maxsize=1)
        self._stopping = threading.Event()
        self._threads = [threading.Thread(target=self._infer_loop, name="gcdtrav-infer", daemon=True)]
        if self.overlap_outputs:
            self._threads.append(threading.Thread(target=self._output_loop, name="gcdtrav-output", daemon=True))
        if triage is not None:
            self._threads.append(threading.Thread(target=self._triage_loop, name="gcdtrav-triage", daemon=True))

    def start(self) -> None:
        for thread in self._threads:
            thread.start()

    def stop(self, deadline: float) -> bool:
        """Finish the frame in flight, by ``deadline`` (monotonic); frames still queued are dropped and counted
        (``shutdown``). True if the threads ended in time: only then may the outputs be closed behind them."""
        self._stopping.set()
        for thread in self._threads:
            if thread.is_alive():
                thread.join(max(0.0, deadline - time.monotonic()))
        for source, count in self.frames.discard_pending().items():
            self.stats.dropped(source, "shutdown", count)
        return not any(thread.is_alive() for thread in self._threads)

    def _infer_loop(self) -> None:
        while not self._stopping.is_set():
            self.progress.beat()
            self.sources.sweep()
            item = self.frames.take(timeout=0.25)
            if item is None:
                continue
            _, pending = item
            self.stats.waited(time.time() - pending.received_at)
            self._guarded(pending, self.on_taken, pending)
            inferred = self._guarded(pending, self._infer, pending)
            if inferred is None:
                continue
            if self.overlap_outputs:
                self._inferred.put(inferred)
            else:
                self._guarded(pending, self._finish, inferred)
        self._inferred.put(None)  # after the frame already handed on

    def _triage_loop(self) -> None:
        assert self.triage is not None
        lower_this_thread(self.settings.reuse.glance_nice)
        while not self._stopping.is_set():
            reusable = self.triage.next_reusable(timeout=0.25)
            if reusable is not None:
                # No beat: answering unchanged views is not inference's progress. A hung inference must
                # still be seen (and its moving robots failed over) while parked ones are answered.
                self._guarded(reusable.pending, self._reuse, reusable, beat=False)

    def _reuse(self, reusable: Reusable) -> None:
        """The source's last maps again, for an unchanged frame: checked like a frame about to be published."""
        assert self.triage is not None
        check_stamp(reusable.seen.stamp)
        self.triage.reuse(reusable, self.gate.before_publish(reusable.pending))

    def _output_loop(self) -> None:
        while (item := self._inferred.get()) is not None:
            self._guarded(item.pending, self._finish, item)

    def _guarded(self, pending: PendingFrame, step: Callable[..., _R], *args: Any, beat: bool = True) -> _R | None:
        """One step of one frame; whatever it raises is counted against the frame, never kills the thread."""
        try:
            return step(*args)
        except RejectedInput as err:
            self.stats.rejected(pending.source, err.reason, err.detail, tracked=self._tracked(pending.source))
        except Dropped as err:
            if err.reason == "stale":
                self.stats.stale(pending.source, err.detail)
            else:
                self.stats.dropped(pending.source, err.reason)
        except Exception as err:
            log.exception("frame from %s failed", pending.key)
            failure = repr(err)[:200]
            self.stats.rejected(pending.source, "processing_failed", failure, tracked=self._tracked(pending.source))
        finally:
            if beat:
                self.progress.beat()
        return None

    def _tracked(self, source: str) -> bool:
        """Whether ``source`` holds a slot: a refused candidate's counts go to the stats' bounded refused list."""
        return self.admission is None or source in self.sources

    def _infer(self, pending: PendingFrame) -> InferredFrame | None:
        """Decoded and inferred; the gate raises (counted) for a frame not worth computing."""
        decoded = self._decode_admitted(pending)
        if decoded is None:
            return None
        image, ros_header = decoded
        self.gate.before_inference(pending, image)
        return InferredFrame(pending, image, ros_header, self.pipeline.infer(image.image))

    def _decode_admitted(self, pending: PendingFrame) -> tuple[DecodedFrame, Any] | None:
        """Decoded; a new source takes its slot only now (or, if its frame fails, is forgotten at once).
        None: it failed and was already counted (evicted as a candidate while it was being taken)."""
        if self.admission is None:
            return self._decode(pending)
        self.admission.taken(pending.source)
        try:
            decoded = self._decode(pending)
        except Exception:
            if self.admission.undecodable(pending.source):
                raise
            return None
        self.admission.decoded(pending.source)
        return decoded

    def _decode(self, pending: PendingFrame) -> tuple[DecodedFrame, Any]:
        """The image and, for ROS inputs, the message header to reuse on the ROS outputs."""
        limits = self.settings.max_payload_bytes, self.settings.max_pixels
        if pending.ros is None:
            return decode_payload(pending.payload, pending.encoding, pending.received_at, *limits), None
        if pending.ros.msgtype is None:
            raise RejectedInput("unsupported_ros_type", f"no message type for '{pending.key}'")
        ros_frame = ros_io.decode_ros_image(pending.payload, pending.ros.msgtype, self.settings.max_pixels)
        return DecodedFrame(ros_frame.image, ros_frame.stamp, ros_frame.frame_id), ros_frame.header

    def _finish(self, inferred: InferredFrame) -> None:
        """Engine, numbering and history, the grid, outputs, counters."""
        source, image = inferred.pending.source, inferred.image
        self.gate.before_publish(inferred.pending)
        result = self.pipeline.finish(inferred.inference)
        maps = result.maps
        record = self.history.record(
            source, maps.weights, result.anchors, image.stamp, image.frame_id, image.camera_size, maps.match
        )
        map_age_s = self.gate.before_publish(inferred.pending)  # the engine took time too
        done = ProcessedFrame(inferred, result, record, self._fuse(inferred.pending, inferred.image, result, record))
        # The glance's reference is set once the maps are kept for reuse and before they go out: a frame sent
        # the moment they are seen is compared with this one and answered with its maps, not inferred again.
        if not self.publish(done, self.triage.inferred if self.triage is not None else _no_reference):
            self.stats.dropped(source, "shutdown")  # finished after the outputs closed
            return
        latency_ms = (time.time() - inferred.pending.received_at) * 1e3
        self.stats.processed(source, record.seq, latency_ms, result.inference_ms, map_age_s)

    def _fuse(
        self, pending: PendingFrame, image: DecodedFrame, result: FrameResult, record: FrameRecord
    ) -> FusedGrid | None:
        """Fuse an inferred frame about to be published into the grid its camera feeds (if any); a reused
        frame (triage) is no new evidence and never reaches here."""
        if self.grids is None:
            return None
        maps = result.maps
        unstamped = pending.stamp is None  # a bare image: stamped with its receipt
        return self.grids.fuse(pending.source, record, maps.weights, maps.match, pending.ros, image.image, unstamped)


def _no_reference(done: ProcessedFrame) -> None:
    """Without a glance, no reference to set."""


def lower_this_thread(nice: int) -> bool:
    """Raise the calling thread's niceness by ``nice`` (Linux: priorities are per thread); False where the
    platform cannot. The glance then runs on what inference leaves idle instead of pre-empting one of its
    threads, which stalls the whole parallel step (benchmarks/README.md, *A mixed fleet*)."""
    if nice <= 0 or not sys.platform.startswith("linux"):
        return False
    tid = threading.get_native_id()
    try:
        os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + nice))
    except OSError as err:
        log.warning("could not lower the glance thread's priority (%s): it competes with inference", err)
        return False
    return True
