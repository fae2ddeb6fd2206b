"""A tf tree without ROS: static links, a time-buffered dynamic part, lookups at a stamp through the tree.

As tf2's BufferCore: each child frame has one parent; a static link holds for every stamp, a dynamic one is a
history bounded by ``buffer_s`` (tf2's default cache time is 10 s) and interpolated between the samples around
the stamp (translation linear, rotation slerp); no extrapolation: a stamp before the oldest sample or after the
newest of a dynamic link on the way is an error naming the link. A sample older than its link's newest minus
``buffer_s`` is refused (tf2: TF_OLD_DATA); out-of-order samples inside the buffer are inserted in order. A link
switching between static and dynamic, or to another parent, starts afresh (tf2 replaces the frame's cache).
Not thread-safe: its owner locks.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field

from gcdtrav.schemas.inputs import RejectedInput
from gcdtrav.service.ros.tf import StampedTransform, Transform, interpolate

MAX_FRAMES = 1000  # child frames per tree: a real robot has tens; invented names cannot grow memory
MAX_SAMPLES_PER_LINK = 2000  # 200 Hz for the default 10 s buffer
MAX_DEPTH = 100  # links from a frame to its root; deeper is a loop (tf2's MAX_GRAPH_DEPTH is 1000)
STAMP_EPS = 1e-6  # stamps equal within a microsecond (CDR stamps are ns; floats lose the last digits)


class TfLookupError(Exception):
    """A lookup the tree cannot answer: ``reason`` is one of tf_unknown_frame, tf_no_chain, tf_loop,
    tf_extrapolation_past, tf_extrapolation_future."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason, self.detail = reason, detail


@dataclass
class _Link:
    parent: str
    static: Transform | None = None
    stamps: list[float] = field(default_factory=list)  # sorted; dynamic links only
    transforms: list[Transform] = field(default_factory=list)

    def at(self, child: str, stamp: float) -> Transform:
        if self.static is not None:
            return self.static
        stamps = self.stamps
        if stamp < stamps[0] - STAMP_EPS:
            raise TfLookupError(
                "tf_extrapolation_past", f"'{self.parent}' -> '{child}' at {stamp:.3f}: oldest is {stamps[0]:.3f}"
            )
        if stamp > stamps[-1] + STAMP_EPS:
            raise TfLookupError(
                "tf_extrapolation_future", f"'{self.parent}' -> '{child}' at {stamp:.3f}: newest is {stamps[-1]:.3f}"
            )
        index = bisect.bisect_left(stamps, stamp)
        if index < len(stamps) and abs(stamps[index] - stamp) <= STAMP_EPS:
            return self.transforms[index]
        if index == 0:  # within STAMP_EPS before the oldest
            return self.transforms[0]
        if index == len(stamps):
            return self.transforms[-1]
        before, after = stamps[index - 1], stamps[index]
        return interpolate(self.transforms[index - 1], self.transforms[index], (stamp - before) / (after - before))


class TransformTree:
    """Frames linked child -> parent by static transforms (/tf_static) and buffered dynamic ones (/tf)."""

    def __init__(self, buffer_s: float = 10.0) -> None:
        self.buffer_s = buffer_s
        self._links: dict[str, _Link] = {}

    def __contains__(self, frame: str) -> bool:
        return frame in self._links or any(link.parent == frame for link in self._links.values())

    def add(self, item: StampedTransform, static: bool) -> None:
        """Insert one checked transform; RejectedInput tf_old_data or tf_too_many_frames if it is not kept."""
        link = self._links.get(item.child)
        if link is None or link.parent != item.parent or (link.static is not None) != static:
            if link is None and len(self._links) >= MAX_FRAMES:
                raise RejectedInput("tf_too_many_frames", f"'{item.child}': the tree holds {MAX_FRAMES} frames")
            link = self._links[item.child] = _Link(item.parent)
        if static:
            link.static = item.transform
            return
        if link.stamps and item.stamp < link.stamps[-1] - self.buffer_s:
            raise RejectedInput(
                "tf_old_data",
                f"'{item.parent}' -> '{item.child}' at {item.stamp:.3f}: older than the buffer "
                f"({self.buffer_s:g} s before {link.stamps[-1]:.3f})",
            )
        index = bisect.bisect_left(link.stamps, item.stamp)
        if index < len(link.stamps) and abs(link.stamps[index] - item.stamp) <= STAMP_EPS:
            link.transforms[index] = item.transform  # the same stamp again: the newer message wins
            return
        link.stamps.insert(index, item.stamp)
        link.transforms.insert(index, item.transform)
        newest = link.stamps[-1]
        drop = bisect.bisect_left(link.stamps, newest - self.buffer_s)
        drop = max(drop, len(link.stamps) - MAX_SAMPLES_PER_LINK)
        if drop > 0:
            del link.stamps[:drop], link.transforms[:drop]

    def lookup(self, target: str, source: str, stamp: float | None = None) -> Transform:
        """The transform taking points in ``source`` to ``target`` at ``stamp`` (None: the latest time every
        dynamic link on the way knows, tf2's lookup at time 0)."""
        up_source, up_target = self._path(target, source)
        if stamp is None:  # None again only when every link is static: any stamp gives the same
            stamp = self._latest_common(up_source + up_target)
        at = 0.0 if stamp is None else stamp
        return self._compose(up_target, at).inverse().then(self._compose(up_source, at))

    def latest_common_time(self, target: str, source: str) -> float | None:
        """The newest stamp at which ``lookup`` can answer (None: every link on the way is static, any stamp)."""
        up_source, up_target = self._path(target, source)
        return self._latest_common(up_source + up_target)

    # ---- the way between two frames -------------------------------------------------------------------
    def _ancestors(self, frame: str) -> list[str]:
        """The frames from ``frame`` up to its root: [frame, parent, ..., root]."""
        if frame not in self:
            raise TfLookupError("tf_unknown_frame", f"no transform names '{frame}' (yet)")
        chain = [frame]
        while chain[-1] in self._links:
            chain.append(self._links[chain[-1]].parent)
            if len(chain) > MAX_DEPTH:
                raise TfLookupError("tf_loop", f"'{frame}' is {MAX_DEPTH} links from any root: a loop")
        return chain

    def _path(self, target: str, source: str) -> tuple[list[str], list[str]]:
        """The child frames from ``source`` and from ``target`` up to their nearest common ancestor."""
        from_source, from_target = self._ancestors(source), self._ancestors(target)
        on_target = set(from_target)
        common = next((frame for frame in from_source if frame in on_target), None)
        if common is None:
            raise TfLookupError(
                "tf_no_chain",
                f"'{source}' reaches '{from_source[-1]}', '{target}' reaches '{from_target[-1]}': "
                "no transform links the two trees",
            )
        return from_source[: from_source.index(common)], from_target[: from_target.index(common)]

    def _compose(self, children: list[str], stamp: float) -> Transform:
        """The transform from the first of ``children`` to the parent of the last (the identity for none)."""
        result = Transform()
        for child in reversed(children):
            result = result.then(self._links[child].at(child, stamp))
        return result

    def _latest_common(self, children: list[str]) -> float | None:
        dynamic = [(child, self._links[child]) for child in children if self._links[child].static is None]
        if not dynamic:
            return None
        newest = min(link.stamps[-1] for _, link in dynamic)
        oldest = max(link.stamps[0] for _, link in dynamic)
        if oldest > newest + STAMP_EPS:
            names = ", ".join(f"'{link.parent}' -> '{child}'" for child, link in dynamic)
            raise TfLookupError("tf_extrapolation_past", f"the buffers of {names} do not overlap in time")
        return newest
