"""Maps out: T and U of one frame, and the header that says which frame, when and from what."""

from __future__ import annotations

from gcdtrav.schemas.config import Method
from gcdtrav.schemas.messages.base import Message
from gcdtrav.schemas.strict import WireModel
from pydantic import Field


class MapsHeader(WireModel):
    source: str = Field(description="The source: the input key after the matched prefix, e.g. 'r1/front'.")
    key: str = Field(description="The full key the image arrived on.")
    seq: int = Field(description="Per-source sequence number of processed frames, from 0.")
    stamp: float = Field(description="Input capture time (envelope stamp, or receive time for bare images), s.")
    frame_id: str = ""
    received_at: float = Field(description="When the service received the image, s since epoch.")
    published_at: float = Field(description="When the service published this message, s since epoch.")
    inference_ms: float = Field(description="Model forward time for this frame, ms.")
    model: str
    instance: str = Field(description="The service instance that made this result.")
    anchor_set_version: str
    method: Method
    map_shape: tuple[int, int] = Field(description="(height, width) of T and U in this message.")
    image_size: tuple[int, int] = Field(
        description="(width, height) of the camera's image, pixels: the input's, or the original_size a relay sent "
        "with a shrunk frame. Pixel coordinates of queries are in it."
    )
    scale: tuple[float, float] = Field(description="(sx, sy): image_size pixels per patch along x and y.")
    order: tuple[float, float] | None = Field(
        default=None,
        description="The source's order across instances and hand-overs: (stamp, received_at), compared as a "
        "tuple; a map whose order is not above the last one shown of its source is older (or the same frame "
        "again) and is dropped by the client. seq counts per instance and does not order. Since 1.2.",
    )
    computed_from: tuple[float, int] | None = Field(
        default=None,
        description="(stamp, seq) of the frame these maps were computed from when it is not this one: this "
        "frame's view had not changed since, so it was not inferred and that frame's maps were published again "
        "(seq is then that frame's; stamp and order are this frame's). None: computed from this frame. Since 1.3.",
    )
    age_at_receipt_s: float | None = Field(
        default=None,
        description="How old the frame was when the service received it, as the service judged it (never "
        "negative): its delay beyond its source's smallest recent one (clock: estimated, whatever the robot's "
        "clock reads), or the service's clock minus the stamp (clock: synced). None: no usable stamp, or a "
        "writer before 1.4. Maps.age_s adds the time since on clocks that need not agree. Since 1.4.",
    )


class MapsMessage(Message):
    """T and U of one frame: 16-bit PNGs, value = round(x * 65535)."""

    header: MapsHeader
    traversability_png: bytes
    uncertainty_png: bytes
    traversability_full_png: bytes | None = Field(default=None, description="At image size, if enabled.")
    uncertainty_full_png: bytes | None = None


class CompactMapsMessage(Message):
    """T and U of one frame for slow links: 8-bit PNGs, value = round(x * 255), at ``header.map_shape`` (the
    model's map, or smaller: ``compact_maps_max_side``), ``header.scale`` for that shape."""

    header: MapsHeader
    traversability_png: bytes
    uncertainty_png: bytes
