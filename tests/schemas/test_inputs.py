"""An input payload's rejection reasons: each counted under its own name, the envelope's kept."""

from __future__ import annotations

import time

import cv2
import msgpack
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


# ---- which payload is which (issue 36: a bare PNG was taken for an envelope) -----------------------------

IMAGE = np.zeros((20, 30, 3), np.uint8)
IMAGE[:, :15] = (200, 40, 10)  # a left half of another colour: the decoded orientation is checked


def jpeg(image: np.ndarray) -> bytes:
    return cv2.imencode(".jpg", image[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 100])[1].tobytes()


def envelope(encoding: str, data: bytes) -> bytes:
    return ImageEnvelope(stamp=123.5, frame_id="cam", encoding=encoding, width=30, height=20, data=data).pack()


# (name, payload, its right zenoh encoding, a wrong one, stamp expected, what decoding must give)
FORMS = [
    ("bare png", encode_png(IMAGE), "image/png", "application/msgpack", None),
    ("bare jpeg", jpeg(IMAGE), "image/jpeg", "application/msgpack", None),
    ("bare bmp", bmp(IMAGE[:, :, ::-1]), "image/bmp", "application/msgpack", None),
    ("bare png labelled jpeg", encode_png(IMAGE), "image/png", "image/jpeg", None),
    ("envelope png", envelope("png", encode_png(IMAGE)), "application/msgpack", "text/plain", 123.5),
    ("envelope jpeg", envelope("jpeg", jpeg(IMAGE)), "application/msgpack", "text/plain", 123.5),
    ("envelope rgb8", envelope("rgb8", IMAGE.tobytes()), "application/msgpack", "text/plain", 123.5),
    ("envelope bgr8", envelope("bgr8", IMAGE[:, :, ::-1].tobytes()), "application/msgpack", "text/plain", 123.5),
]
UNSET = ["", "zenoh/bytes", "application/octet-stream"]


@pytest.mark.parametrize("encoding_case", ["set", *UNSET, "wrong"])
@pytest.mark.parametrize(("name", "payload", "right", "wrong", "stamp"), FORMS, ids=[f[0] for f in FORMS])
def test_every_input_form_is_told_apart_under_every_encoding(
    name: str, payload: bytes, right: str, wrong: str, stamp: float | None, encoding_case: str
) -> None:
    """Decoder and age peek agree, and each form decodes to its pixels, whatever the encoding says, as long
    as it does not contradict a form that has no signature (see the next test)."""
    from gcdtrav.schemas.inputs import input_kind
    from gcdtrav.service.runtime.intake.frame_age import input_times

    encoding = {"set": right, "wrong": wrong}.get(encoding_case, encoding_case)
    kind = "envelope" if name.startswith("envelope") else "image"
    assert input_kind(payload, encoding) == kind
    decoded = decode_payload(payload, encoding, received_at=7.0, max_bytes=10**7, max_pixels=10**6)
    assert decoded.image.shape == (20, 30, 3)
    assert np.abs(decoded.image[10, 5].astype(int) - (200, 40, 10)).max() <= 3  # RGB, left half
    assert np.abs(decoded.image[10, 25].astype(int)).max() <= 3
    assert decoded.stamp == (stamp if stamp is not None else 7.0)
    assert input_times(payload, encoding, ros=False).stamp == stamp  # the peek reads the same stamp


def test_a_form_without_a_signature_follows_a_wrong_encoding_and_says_why_it_failed() -> None:
    """An envelope labelled as an image is decoded as the image it claims to be: rejected, not guessed."""
    from gcdtrav.schemas.inputs import image_format, input_kind

    wrapped = envelope("png", encode_png(IMAGE))
    assert input_kind(wrapped, "image/png") == "image" and image_format(wrapped) is None
    with pytest.raises(RejectedInput) as rejected:
        decode_payload(wrapped, "image/png", 0.0, 10**7, 10**6)
    assert rejected.value.reason == "undecodable"
    with pytest.raises(RejectedInput) as garbage:
        decode_payload(b"\x00junk", "zenoh/bytes", 0.0, 10**7, 10**6)
    assert garbage.value.reason == "undecodable"
    assert [image_format(p) for p in (encode_png(IMAGE), jpeg(IMAGE), bmp(IMAGE), b"GIF89a..", b"RIFFxxxxWEBP")] == [
        "PNG", "JPEG", "BMP", "GIF", "WebP"
    ]  # fmt: skip


def test_the_bug_a_bare_png_was_a_malformed_envelope() -> None:
    """PNG's first byte 0x89 is msgpack's fixmap of 9 entries; the signature must decide before msgpack."""
    png = encode_png(IMAGE)
    assert png[0] == 0x89
    assert decode_payload(png, "zenoh/bytes", 1.0, 10**7, 10**6).image.shape == (20, 30, 3)


def test_an_original_size_is_kept_and_bounded() -> None:
    """A relay's shrunk frame says the camera's size: kept for the geometry, under the same pixel limit."""
    from gcdtrav.schemas.messages import MessageError

    def shrunk(original: tuple[int, int]) -> bytes:
        return ImageEnvelope(
            stamp=1.0, encoding="png", width=30, height=20, data=encode_png(IMAGE), original_size=original
        ).pack()

    decoded = decode_payload(shrunk((1920, 1280)), "application/msgpack", 0.0, 10**7, 1920 * 1280)
    assert decoded.image.shape == (20, 30, 3) and decoded.camera_size == (1920, 1280)
    assert decode_payload(encode_png(IMAGE), "", 0.0, 10**7, 10**6).camera_size == (30, 20)
    with pytest.raises(RejectedInput) as rejected:
        decode_payload(shrunk((1921, 1280)), "application/msgpack", 0.0, 10**7, 1920 * 1280)
    assert rejected.value.reason == "too_many_pixels" and "1921x1280" in rejected.value.detail
    fields = ImageEnvelope.unpack(shrunk((10, 20))).model_dump() | {"original_size": (0, 20)}
    with pytest.raises(MessageError, match="original_size"):
        ImageEnvelope.unpack(msgpack.packb(fields, use_bin_type=True))
