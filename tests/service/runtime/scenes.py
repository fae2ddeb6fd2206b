"""Synthetic camera views for the change measure's tests: a textured scene, its noise, flicker and intruders."""

from __future__ import annotations

import time

import numpy as np
from gcdtrav.schemas.images import encode_jpeg
from gcdtrav.service.runtime.frames import PendingFrame
from numpy.typing import NDArray

HEIGHT, WIDTH = 480, 640


def scene(seed: int = 0, shift: int = 0) -> NDArray[np.uint8]:
    """A smooth textured view (mid grey levels, so flicker does not clip); ``shift`` pans it by pixels."""
    rng = np.random.default_rng(seed)
    coarse = rng.uniform(60, 190, (HEIGHT // 40 + 2, WIDTH // 40 + 4, 3)).astype(np.float32)
    import cv2

    big = cv2.resize(coarse, (coarse.shape[1] * 40, coarse.shape[0] * 40), interpolation=cv2.INTER_CUBIC)
    return np.clip(big[:HEIGHT, shift : shift + WIDTH], 0, 255).astype(np.uint8)


def noisy(image: NDArray[np.uint8], sigma: float, seed: int) -> NDArray[np.uint8]:
    rng = np.random.default_rng(seed)
    return np.clip(image + rng.normal(0, sigma, image.shape), 0, 255).astype(np.uint8)


def flicker(image: NDArray[np.uint8], gain: float, offset: float) -> NDArray[np.uint8]:
    return np.clip(image.astype(np.float32) * gain + offset, 0, 255).astype(np.uint8)


def with_person(image: NDArray[np.uint8], left: int = 300, width: int = 60, height: int = 200) -> NDArray[np.uint8]:
    """A dark upright figure standing in the view (a person walking in)."""
    out = image.copy()
    out[HEIGHT - height - 40 : HEIGHT - 40, left : left + width] = (30, 40, 200)
    return out


def jpeg_frame(image: NDArray[np.uint8], source: str = "r1/front", received_at: float | None = None) -> PendingFrame:
    received = time.time() if received_at is None else received_at
    return PendingFrame(source, f"gcdtrav/in/{source}", encode_jpeg(image, 90), "image/jpeg", received)
