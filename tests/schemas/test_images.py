from __future__ import annotations

import cv2
import numpy as np
import pytest
from conftest import textured_image
from gcdtrav.schemas.images import (
    ImageDecodeError,
    decode_image,
    decode_map_png16,
    encode_jpeg,
    encode_map_png16,
    encode_png,
    peek_image_size,
)


def test_peek_size_png_and_jpeg() -> None:
    image = textured_image(37, 53)
    assert peek_image_size(encode_png(image)) == (53, 37)
    assert peek_image_size(encode_jpeg(image)) == (53, 37)
    assert peek_image_size(b"not an image") is None


def test_decode_round_trip_is_rgb() -> None:
    image = textured_image(20, 30)
    np.testing.assert_array_equal(decode_image(encode_png(image)), image)
    mono = cv2.imencode(".png", image[:, :, 0])[1].tobytes()
    assert decode_image(mono).shape == (20, 30, 3)


def test_decode_errors() -> None:
    with pytest.raises(ImageDecodeError, match="empty"):
        decode_image(b"")
    with pytest.raises(ImageDecodeError, match="not a decodable image"):
        decode_image(b"\x89PNG\r\n\x1a\ntruncated")
    big = encode_png(np.zeros((100, 200, 3), np.uint8))
    with pytest.raises(ImageDecodeError, match="200x100 pixels exceeds"):
        decode_image(big, max_pixels=10_000)
    truncated = encode_jpeg(textured_image(64, 64))[:40]
    with pytest.raises(ImageDecodeError):
        decode_image(truncated)


def test_map_png16_is_lossless_to_one_quantum(rng: np.random.Generator) -> None:
    values = rng.uniform(0, 1, size=(44, 44)).astype(np.float32)
    decoded = decode_map_png16(encode_map_png16(values))
    assert decoded.shape == values.shape
    assert np.max(np.abs(decoded - values)) <= 0.5 / 65535 + 1e-7
    with pytest.raises(ImageDecodeError):
        decode_map_png16(encode_png(textured_image(4, 4)))
