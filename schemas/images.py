"""Image and map byte formats, and the colour maps of T and U, shared by the service, the offline CLI and the
client."""

from __future__ import annotations

import struct
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import cv2
import numpy as np
from gcdtrav.schemas.messages import MessageError
from numpy.typing import NDArray

MAP_QUANTUM = 65535  # maps travel as 16-bit PNGs: value = round(x * 65535), x clipped to [0, 1]
COMPACT_QUANTUM = 255  # compact maps (maps8): 8-bit PNGs, value = round(x * 255)


class ImageDecodeError(ValueError):
    """Bytes that are not a usable image; the message says why, ``reason`` is its code for counting."""

    def __init__(self, message: str, reason: str = "undecodable") -> None:
        super().__init__(message)
        self.reason = reason


def png_bytes(array: NDArray[Any], params: Sequence[int] = ()) -> bytes:
    """``array`` (as OpenCV orders its channels) as a PNG file."""
    ok, buffer = cv2.imencode(".png", array, list(params))
    if not ok:
        raise ValueError("PNG encoding failed")
    return bytes(buffer.tobytes())


def png_array(data: bytes) -> NDArray[Any] | None:
    """A PNG's pixels as stored (bit depth and channels kept); None if ``data`` is not a readable image."""
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)


def peek_image_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a PNG or JPEG header without decoding pixels; None if not recognised.

    Lets a server refuse a decompression bomb before allocating its pixels.
    """
    if data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) >= 24 and data[12:16] == b"IHDR":
        width, height = struct.unpack(">II", data[16:24])
        return int(width), int(height)
    if data[:2] == b"\xff\xd8":
        index = 2
        while index + 9 <= len(data):
            if data[index] != 0xFF:
                return None
            marker = data[index + 1]
            if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
                index += 2
                continue
            (length,) = struct.unpack(">H", data[index + 2 : index + 4])
            # SOF0..SOF15 except DHT (C4), JPG (C8) and DAC (CC) carry the frame size.
            if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
                height, width = struct.unpack(">HH", data[index + 5 : index + 9])
                return int(width), int(height)
            index += 2 + length
    return None


def decode_image(data: bytes, max_pixels: int | None = None) -> NDArray[np.uint8]:
    """JPEG/PNG/any OpenCV-readable bytes to an (H, W, 3) uint8 RGB array."""
    if not data:
        raise ImageDecodeError("empty payload (0 bytes)", "empty")
    size = peek_image_size(data)
    if size is not None and max_pixels is not None and size[0] * size[1] > max_pixels:
        raise ImageDecodeError(
            f"image of {size[0]}x{size[1]} pixels exceeds the limit of {max_pixels} pixels", "too_many_pixels"
        )
    buffer = np.frombuffer(data, dtype=np.uint8)
    try:
        image = cv2.imdecode(buffer, cv2.IMREAD_COLOR)
    except cv2.error as err:
        raise ImageDecodeError(f"not a decodable image ({str(err).strip()[:120]})") from None
    if image is None:
        raise ImageDecodeError(f"not a decodable image ({len(data)} bytes, starts with {data[:8]!r})")
    if image.size == 0:
        raise ImageDecodeError("image has zero size")
    if max_pixels is not None and image.shape[0] * image.shape[1] > max_pixels:  # a header peek could not tell
        raise ImageDecodeError(
            f"image of {image.shape[1]}x{image.shape[0]} pixels exceeds the limit of {max_pixels} pixels",
            "too_many_pixels",
        )
    return np.asarray(cv2.cvtColor(image, cv2.COLOR_BGR2RGB), dtype=np.uint8)


def encode_jpeg(image_rgb: NDArray[np.uint8], quality: int = 90) -> bytes:
    ok, buffer = cv2.imencode(".jpg", cv2.cvtColor(image_rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return buffer.tobytes()


def encode_png(image_rgb: NDArray[np.uint8]) -> bytes:
    return png_bytes(cv2.cvtColor(image_rgb, cv2.COLOR_RGB2BGR))


def resize_map(values: NDArray[np.floating], width: int, height: int) -> NDArray[np.float32]:
    """A map at another resolution (bilinear), e.g. from the decoder's 352x352 to the image's size."""
    resized = cv2.resize(np.asarray(values, np.float32), (width, height), interpolation=cv2.INTER_LINEAR)
    return np.asarray(resized, dtype=np.float32)


def quantize_map(values: NDArray[np.floating]) -> NDArray[np.uint16]:
    return np.round(np.clip(values, 0.0, 1.0) * MAP_QUANTUM).astype(np.uint16)


def encode_map_png16(values: NDArray[np.floating]) -> bytes:
    """A [0, 1] map as a lossless single-channel 16-bit PNG (resolution 1/65535)."""
    # Run-length deflate at level 1 after the Average filter: on 16-bit maps as small (within 4 %) as
    # libpng's adaptive filters with the default strategy at level 3, in a third of the time; encoding is
    # on the service's per-frame path (benchmarks/README.md).
    params = [
        cv2.IMWRITE_PNG_COMPRESSION, 1,
        cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE,
        cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_AVG,
    ]  # fmt: skip
    return png_bytes(quantize_map(values), params)


_ENCODERS = ThreadPoolExecutor(max_workers=2, thread_name_prefix="png")


def encode_maps_png16(*maps: NDArray[np.floating]) -> list[bytes]:
    """Several maps encoded concurrently (OpenCV releases the GIL while compressing)."""
    return list(_ENCODERS.map(encode_map_png16, maps))


def encode_all(jobs: Sequence[tuple[Callable[[NDArray[Any]], bytes], NDArray[Any]]]) -> list[bytes]:
    """Each (encoder, values) encoded concurrently, in order (a grid's layers, schemas/grid_layers.py)."""
    return list(_ENCODERS.map(lambda job: job[0](job[1]), jobs))


def decode_map_png16(data: bytes) -> NDArray[np.float32]:
    image = png_array(data)
    if image is None or image.dtype != np.uint16 or image.ndim != 2:
        raise ImageDecodeError("not a single-channel 16-bit PNG map")
    return image.astype(np.float32) / np.float32(MAP_QUANTUM)


def encode_map_png8(values: NDArray[np.floating], size: tuple[int, int] | None = None) -> bytes:
    """A [0, 1] map as an 8-bit PNG (resolution 1/255), optionally resized first to ``size`` (width, height)."""
    array = np.asarray(values, np.float32)
    if size is not None and size != (array.shape[1], array.shape[0]):
        array = np.asarray(cv2.resize(array, size, interpolation=cv2.INTER_AREA), np.float32)
    quantised = np.round(np.clip(array, 0.0, 1.0) * COMPACT_QUANTUM).astype(np.uint8)
    return png_bytes(quantised, [cv2.IMWRITE_PNG_COMPRESSION, 6])


def decode_map_png8(data: bytes) -> NDArray[np.float32]:
    image = png_array(data)
    if image is None or image.dtype != np.uint8 or image.ndim != 2:
        raise ImageDecodeError("not a single-channel 8-bit PNG map")
    return image.astype(np.float32) / np.float32(COMPACT_QUANTUM)


# ---- colour maps: the service's preview and the viewer (gcdtrav view) look alike ---------------------

UNCERTAINTY_VMAX = 0.5  # U's colour scale ends here: sigma of two equal peaks at 0 and 1

# Red (untraversable) -> yellow -> green (ideal ground), as a 256-entry RGB lookup table.
_STOPS = np.array(
    [[0.0, 165, 0, 38], [0.25, 244, 109, 67], [0.5, 254, 224, 139], [0.75, 102, 189, 99], [1.0, 0, 104, 55]],
    dtype=np.float32,
)
_TRAV_LUT = np.stack([np.interp(np.linspace(0, 1, 256), _STOPS[:, 0], _STOPS[:, c]) for c in (1, 2, 3)], axis=1).astype(
    np.uint8
)


def colorize_traversability(t: NDArray[np.floating]) -> NDArray[np.uint8]:
    index = np.round(np.clip(t, 0, 1) * 255).astype(np.uint8)
    return _TRAV_LUT[index]


def colorize_uncertainty(u: NDArray[np.floating], vmax: float = UNCERTAINTY_VMAX) -> NDArray[np.uint8]:
    """Dark = certain, bright = ambiguous (inferno); vmax 0.5 is sigma of two peaks at 0 and 1."""
    index = np.round(np.clip(u / max(vmax, 1e-9), 0, 1) * 255).astype(np.uint8)
    return cv2.cvtColor(cv2.applyColorMap(index, cv2.COLORMAP_INFERNO), cv2.COLOR_BGR2RGB)


def overlay(image_rgb: NDArray[np.uint8], colours: NDArray[np.uint8], alpha: float = 0.55) -> NDArray[np.uint8]:
    """The colours blended over the image (the preview's and `gcdtrav infer`'s overlays)."""
    blended = cv2.addWeighted(image_rgb, 1 - alpha, colours, alpha, 0.0)
    return np.asarray(blended, dtype=np.uint8)


def encode_count_png(count: NDArray[np.integer]) -> bytes:
    """A grid's observation counts as a 16-bit PNG (saturating at 65535)."""
    return png_bytes(np.clip(count, 0, 65535).astype(np.uint16))


def decode_count_png(data: bytes) -> NDArray[np.int64]:
    """The inverse of ``encode_count_png``; MessageError if ``data`` is not a PNG."""
    decoded = png_array(data)
    if decoded is None:
        raise MessageError("grid count layer is not a PNG")
    return decoded.astype(np.int64)


AGE_STEP_S = 0.1  # a grid's age layer travels in tenths of a second
AGE_NEVER = 65535  # the age layer's value of a cell never observed; ages cap one step below (6553.4 s)


def encode_age_png(age_s: NDArray[np.floating]) -> bytes:
    """A grid's cell ages (seconds, NaN: never observed) as a 16-bit PNG of tenths of a second."""
    age = np.asarray(age_s, np.float64)
    with np.errstate(invalid="ignore"):
        steps = np.clip(np.round(np.nan_to_num(age, nan=0.0) / AGE_STEP_S), 0, AGE_NEVER - 1)
    return png_bytes(np.where(np.isnan(age), AGE_NEVER, steps).astype(np.uint16))


def decode_age_png(data: bytes) -> NDArray[np.float32]:
    """The inverse of ``encode_age_png``: seconds, NaN where never observed; MessageError if not a 16-bit PNG."""
    decoded = png_array(data)
    if decoded is None or decoded.dtype != np.uint16 or decoded.ndim != 2:
        raise MessageError("grid age layer is not a single-channel 16-bit PNG")
    return np.where(decoded == AGE_NEVER, np.nan, decoded * AGE_STEP_S).astype(np.float32)
