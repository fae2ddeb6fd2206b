"""An input payload's rejection reasons: each counted under its own name, the envelope's kept."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest
from gcdtrav.schemas.images import encode_png
from gcdtrav.schemas.inputs import RejectedInput, decode_payload
from gcdtrav.schemas.messages import ImageEnvelope

RGB = np.zeros((20, 30, 3), np.uint8)


def bmp(image: np.ndarray) -> bytes:
    """A format whose size the header peek does not read: only decoding tells."""
    return cv2.imencode(".bmp", image)[1].tobytes()


@pytest.mark.parametrize("encode", [encode_png, bmp], ids=["png", "bmp"])
def test_an_image_over_max_pixels_is_too_many_pixels_bare_or_in_an_envelope(encode) -> None:  # type: ignore[no-untyped-def]
    data = encode(RGB)
    envelope = ImageEnvelope(stamp=1.0, encoding="png", width=30, height=20, data=data).pack()
    for payload, encoding in ((data, "image/png"), (envelope, "application/msgpack")):
        with pytest.raises(RejectedInput) as rejected:
            decode_payload(payload, encoding, time.time(), max_bytes=10**7, max_pixels=599)
        assert rejected.value.reason == "too_many_pixels" and "exceeds the limit of 599" in rejected.value.detail
    assert decode_payload(data, "image/png", time.time(), 10**7, 600).image.shape == (20, 30, 3)  # at the limit


def test_an_oversized_payload_and_an_envelope_with_garbage_keep_their_reasons() -> None:
    with pytest.raises(RejectedInput, match="oversized"):
        decode_payload(encode_png(RGB), "image/png", 0.0, max_bytes=10, max_pixels=10**6)
    garbage = ImageEnvelope(stamp=1.0, encoding="jpeg", width=30, height=20, data=b"\xff\xd8 not really").pack()
    with pytest.raises(RejectedInput) as rejected:
        decode_payload(garbage, "application/msgpack", 0.0, 10**7, 10**6)
    assert rejected.value.reason == "undecodable" and rejected.value.detail.startswith("envelope jpeg")
