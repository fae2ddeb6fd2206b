"""Write a small synthetic dataset in the GOOSE 2D layout, to try `gcdtrav eval` without the real data.

    python examples/make_synthetic_goose.py /tmp/synthetic-goose --frames 6
    gcdtrav eval --dataset goose --root /tmp/synthetic-goose --out /tmp/eval --model ./clipseg-rd64-refined

Each frame: sky on top, then bands of asphalt, low grass, water and gravel with a bush, each band filled
with a colour and texture loosely like the material. The numbers only mean something with real weights.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

# (GOOSE class id, BGR colour) per band, top to bottom below the sky.
BANDS = [(23, (90, 90, 90)), (50, (40, 160, 60)), (54, (160, 110, 60)), (24, (150, 160, 170))]
SKY, BUSH = 53, 17


def frame(seed: int, height: int = 240, width: int = 320) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    image = np.zeros((height, width, 3), np.uint8)
    ids = np.zeros((height, width), np.uint8)
    horizon = height // 4 + int(rng.integers(-10, 10))
    image[:horizon], ids[:horizon] = (230, 200, 150), SKY
    edges = np.linspace(horizon, height, len(BANDS) + 1).astype(int)
    for (label, colour), top, bottom in zip(BANDS, edges[:-1], edges[1:], strict=True):
        image[top:bottom] = colour
        ids[top:bottom] = label
    x0 = int(rng.integers(0, width - 60))
    image[edges[-2] - 30 : edges[-2], x0 : x0 + 60], ids[edges[-2] - 30 : edges[-2], x0 : x0 + 60] = (30, 90, 40), BUSH
    noise = rng.normal(0, 12, size=image.shape)
    return np.clip(image + noise, 0, 255).astype(np.uint8), ids


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("root", type=Path)
    parser.add_argument("--frames", type=int, default=6)
    parser.add_argument("--split", default="val")
    args = parser.parse_args()
    images, labels = args.root / "images" / args.split / "synthetic", args.root / "labels" / args.split / "synthetic"
    images.mkdir(parents=True, exist_ok=True)
    labels.mkdir(parents=True, exist_ok=True)
    for index in range(args.frames):
        image, ids = frame(index)
        name = f"synthetic__{index:04d}"
        cv2.imwrite(str(images / f"{name}_windshield_vis.png"), image)
        cv2.imwrite(str(labels / f"{name}_labelids.png"), ids)
    print(f"{args.frames} frames written under {args.root}")


if __name__ == "__main__":
    main()
