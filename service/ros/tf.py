"""tf2_msgs/msg/TFMessage over Zenoh: the CDR codec, rigid transforms, and the checks tf2 applies on input.

The topics, their QoS and keys (read from ros2/geometry2 and ros2/rmw_zenoh; docs/grid.md, "Mount and pose from tf"):

  /tf_static   TRANSIENT_LOCAL + RELIABLE, KEEP_LAST 1 per publisher (tf2_ros StaticBroadcasterQoS): each
               static broadcaster republishes every transform it ever sent in one message, so the last message
               of each publisher is its whole set. rmw_zenoh declares it as an AdvancedPublisher with a cache of
               1 sample and publisher detection; a late subscriber gets it by a history query.
  /tf          VOLATILE + RELIABLE, KEEP_LAST 100 (DynamicBroadcasterQoS): a plain zenoh publisher.

  rmw_zenoh                 <domain>/tf/tf2_msgs::msg::dds_::TFMessage_/<type hash>   (tf_static alike)
  zenoh-bridge-ros2dds      tf  and  tf_static   (the bridge caches transient-local topics the same way)

A transform that tf2's BufferCore::setTransform would ignore (frame ids empty or equal, a NaN, a quaternion whose
norm is off by 1e-2 or more) is refused here with the same reason, and the rest of its message is kept. Frame ids
lose a leading '/', as in tf2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from gcdtrav.schemas.inputs import RejectedInput
from gcdtrav.schemas.limits import MAX_FRAME_ID_CHARS
from gcdtrav.service.ros.cdr import typestore, yaw_of_quaternion
from numpy.typing import NDArray

TF_MESSAGE = "tf2_msgs/msg/TFMessage"
QUATERNION_TOLERANCE = 1e-2  # tf2's QUATERNION_NORMALIZATION_TOLERANCE (10e-3) on |q|^2 - 1
MAX_TRANSFORMS_PER_MESSAGE = 10_000  # a robot's whole tree is tens to hundreds of frames


@dataclass(frozen=True)
class Transform:
    """A rigid transform: a point p in the child frame is ``rotate(q, p) + translation`` in the parent frame.
    ``rotation`` is the unit quaternion (x, y, z, w)."""

    translation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)

    def matrix(self) -> NDArray[np.float64]:
        """The 3 x 3 rotation matrix (child axes in the parent frame, as columns)."""
        x, y, z, w = self.rotation
        return np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
            ]
        )

    def then(self, inner: Transform) -> Transform:
        """self ∘ inner: ``inner`` maps a frame C into B, ``self`` maps B into A; the result maps C into A."""
        moved = self.matrix() @ np.asarray(inner.translation)
        t = tuple(float(a + b) for a, b in zip(self.translation, moved, strict=True))
        return Transform((t[0], t[1], t[2]), _multiply(self.rotation, inner.rotation))

    def inverse(self) -> Transform:
        x, y, z, w = self.rotation
        back = -(self.matrix().T @ np.asarray(self.translation))
        return Transform((float(back[0]), float(back[1]), float(back[2])), (-x, -y, -z, w))

    def yaw(self) -> float:
        """The heading of the child's x axis in the parent's xy plane (the grid's 2-D pose)."""
        return yaw_of_quaternion(*self.rotation)


def _multiply(a: tuple[float, ...], b: tuple[float, ...]) -> tuple[float, float, float, float]:
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    )


def interpolate(a: Transform, b: Transform, ratio: float) -> Transform:
    """Translation linear, rotation along the shortest arc (slerp), as tf2's TimeCache interpolates."""
    t = tuple(pa + (pb - pa) * ratio for pa, pb in zip(a.translation, b.translation, strict=True))
    qa, qb = np.asarray(a.rotation), np.asarray(b.rotation)
    dot = float(qa @ qb)
    if dot < 0:  # q and -q are one rotation: take the shorter way round
        qb, dot = -qb, -dot
    if dot > 0.9995:  # nearly equal: linear, normalised (slerp's sine would divide by ~0)
        q = qa + (qb - qa) * ratio
    else:
        angle = math.acos(dot)
        q = (math.sin((1 - ratio) * angle) * qa + math.sin(ratio * angle) * qb) / math.sin(angle)
    q = q / np.linalg.norm(q)
    return Transform((t[0], t[1], t[2]), (float(q[0]), float(q[1]), float(q[2]), float(q[3])))


@dataclass(frozen=True)
class StampedTransform:
    """One transform of a TFMessage: ``child`` in ``parent`` at ``stamp`` (seconds, the sender's clock)."""

    parent: str
    child: str
    stamp: float
    transform: Transform


def strip_slash(frame_id: str) -> str:
    return frame_id[1:] if frame_id.startswith("/") else frame_id


def decode_tf_message(payload: bytes) -> tuple[list[StampedTransform], list[RejectedInput]]:
    """A TFMessage's valid transforms, and a refusal for each one tf2 would ignore. RejectedInput ``bad_tf`` if the
    message itself does not decode (nothing of it is kept)."""
    try:
        message = typestore().deserialize_cdr(payload, TF_MESSAGE)
    except Exception as err:  # rosbags raises assorted errors on truncated or garbled CDR
        raise RejectedInput("bad_tf", f"not a {TF_MESSAGE}: {type(err).__name__}: {err}") from None
    if len(message.transforms) > MAX_TRANSFORMS_PER_MESSAGE:
        raise RejectedInput("bad_tf", f"{len(message.transforms)} transforms, over {MAX_TRANSFORMS_PER_MESSAGE}")
    kept: list[StampedTransform] = []
    refused: list[RejectedInput] = []
    for stamped in message.transforms:
        try:
            kept.append(_checked(stamped))
        except RejectedInput as err:
            refused.append(err)
    return kept, refused


def _checked(stamped: object) -> StampedTransform:
    """One geometry_msgs/TransformStamped, checked as tf2's setTransform does."""
    header, transform = stamped.header, stamped.transform  # type: ignore[attr-defined]
    parent, child = strip_slash(str(header.frame_id)), strip_slash(str(stamped.child_frame_id))  # type: ignore[attr-defined]
    if len(parent) > MAX_FRAME_ID_CHARS or len(child) > MAX_FRAME_ID_CHARS:
        raise RejectedInput("tf_frame_id_too_long", f"a frame id over {MAX_FRAME_ID_CHARS} characters")
    if not parent or not child:
        raise RejectedInput("tf_no_frame_id", f"frame_id '{parent}', child_frame_id '{child}': both must be set")
    if parent == child:
        raise RejectedInput("tf_self_transform", f"'{child}' to itself")
    v, r = transform.translation, transform.rotation
    translation = (float(v.x), float(v.y), float(v.z))
    rotation = (float(r.x), float(r.y), float(r.z), float(r.w))
    stamp = float(header.stamp.sec) + float(header.stamp.nanosec) * 1e-9
    if not all(math.isfinite(value) for value in (*translation, *rotation, stamp)):
        raise RejectedInput("tf_nan", f"'{parent}' -> '{child}': a value that is not finite")
    norm2 = sum(value * value for value in rotation)
    if abs(norm2 - 1.0) >= QUATERNION_TOLERANCE:
        raise RejectedInput("tf_denormalized_quaternion", f"'{parent}' -> '{child}': |q|^2 = {norm2:.4f}")
    if abs(norm2 - 1.0) > 1e-12:  # within tolerance: normalised, so compositions stay rigid
        scale = 1.0 / math.sqrt(norm2)
        rotation = (rotation[0] * scale, rotation[1] * scale, rotation[2] * scale, rotation[3] * scale)
    return StampedTransform(parent, child, stamp, Transform(translation, rotation))
