"""Bounds on free text, documents and coordinates from the bus, in one place: whatever a peer sends is checked
against them.

Each bound is far above any real use and far below what would cost the service memory or time.
"""

import math
from typing import Annotated

from pydantic import AfterValidator

MAX_NAME_CHARS = 200  # an anchor set's name
MAX_CONCEPT_CHARS = 1000  # a concept's text, bounded before its CLIP tokens (at most 75) are counted
MAX_FRAME_ID_CHARS = 256  # a frame id (camera or odometry; ROS frame ids are short names)
MAX_SOURCE_CHARS = 256  # a source name taken from an input key
MAX_DOCUMENT_DEPTH = 32  # nesting of an anchor-set document: a real one is 3 deep
DEFAULT_MAX_ANCHOR_SET_BYTES = 64 * 1024  # an anchor-set body; 64 anchors in JSON take about 4 kB
MAX_POSITION_M = 1e8  # a pose coordinate: UTM northings stay below 1e7 m


def finite(value: float) -> float:
    if not math.isfinite(value):
        raise ValueError(f"{value} is not a finite number")
    return value


def within_reach(value: float) -> float:
    if abs(value) > MAX_POSITION_M:
        raise ValueError(f"{value:g} m is beyond the limit of {MAX_POSITION_M:g} m")
    return value


FiniteFloat = Annotated[float, AfterValidator(finite)]
Coordinate = Annotated[float, AfterValidator(finite), AfterValidator(within_reach)]  # metres in a pose's frame
