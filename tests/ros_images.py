"""ROS 2 Image CDR for the tests of service/ros and service/bus: a camera message as rmw_zenoh carries it."""

from __future__ import annotations

import numpy as np
from conftest import textured_image
from gcdtrav.service.ros import cdr as ros

STAMP = 1_700_000_000.25
RGB = textured_image(24, 32, seed=4)


def image_cdr(
    array: np.ndarray,
    encoding: str,
    stamp: float = STAMP,
    frame_id: str = "cam",
    step: int | None = None,
    data: np.ndarray | None = None,
    width: int | None = None,
    height: int | None = None,
) -> bytes:
    header = ros.make_header(stamp, frame_id)
    flat = np.ascontiguousarray(array).view(np.uint8).reshape(array.shape[0], -1)
    row = flat.shape[1]
    if step is not None and step > row:
        flat = np.concatenate([flat, np.full((flat.shape[0], step - row), 7, np.uint8)], axis=1)
    payload = flat.ravel() if data is None else data
    message = ros.typestore().types[ros.IMAGE](
        header=header,
        height=height or array.shape[0],
        width=width or array.shape[1],
        encoding=encoding,
        is_bigendian=0,
        step=step or row,
        data=payload,
    )
    return bytes(ros.typestore().serialize_cdr(message, ros.IMAGE))
