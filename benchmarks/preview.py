"""The preview's cost per frame, as the service drew it before 1.1 (T and U upsampled to the image's size,
overlaid, the panel shrunk) and now (T and U resized straight to the preview's size), interleaved in one
process; and the ROS rgb preview, before (a decode of the JPEG just encoded) and now (the panel itself).

    python -m benchmarks.preview [--width 1920 --height 1200 --rounds 30]
"""

from __future__ import annotations

import argparse
import json
import platform

import cv2
import numpy as np
from gcdtrav.schemas import images as viz
from gcdtrav.schemas.images import decode_image, encode_jpeg, resize_map
from gcdtrav.service.backends.cpus import cpu_name
from gcdtrav.service.backends.timing import interleaved_ms
from gcdtrav.service.runtime.outputs import PREVIEW_JPEG_QUALITY, preview_panel


def preview_before(image: np.ndarray, t: np.ndarray, u: np.ndarray, max_width: int) -> bytes:
    """gcdtrav 0.1.0's FrameOutputs.publish + preview_jpeg, verbatim in effect."""
    height, width = image.shape[:2]
    t_full, u_full = resize_map(t, width, height), resize_map(u, width, height)
    panel = np.concatenate(
        [viz.overlay(image, viz.colorize_traversability(t_full)), viz.colorize_uncertainty(u_full)], 1
    )
    if panel.shape[1] > max_width:
        size = (max_width, max(1, round(panel.shape[0] * max_width / panel.shape[1])))
        panel = cv2.resize(panel, size, interpolation=cv2.INTER_AREA)
    return encode_jpeg(panel, quality=PREVIEW_JPEG_QUALITY)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--width", type=int, default=1920)
    parser.add_argument("--height", type=int, default=1200)
    parser.add_argument("--max-width", type=int, default=640)
    parser.add_argument("--rounds", type=int, default=30)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (args.height, args.width, 3), dtype=np.uint8)
    t, u = rng.random((352, 352), dtype=np.float32), rng.random((352, 352), dtype=np.float32) * 0.4

    def now() -> bytes:
        return encode_jpeg(preview_panel(image, t, u, args.max_width), PREVIEW_JPEG_QUALITY)

    def rgb_before() -> np.ndarray:
        return decode_image(now())

    def rgb_now() -> np.ndarray:
        panel = preview_panel(image, t, u, args.max_width)
        encode_jpeg(panel, PREVIEW_JPEG_QUALITY)  # the compressed preview is still made once
        return panel

    calls = {
        "preview before": lambda: preview_before(image, t, u, args.max_width),
        "preview now": now,
        "ROS rgb preview before": rgb_before,
        "ROS rgb preview now": rgb_now,
    }
    medians = {name: float(np.median(times)) for name, times in interleaved_ms(calls, args.rounds).items()}
    print(
        f"CPU {cpu_name()} ({platform.machine()}), image {args.width}x{args.height}, preview {args.max_width} px wide"
    )
    print("| step | median ms |\n|---|---:|")
    for name, ms in medians.items():
        print(f"| {name} | {ms:.2f} |")
    print(
        f"preview: {medians['preview before'] / medians['preview now']:.1f}x faster; ROS rgb preview: "
        f"{medians['ROS rgb preview before'] / medians['ROS rgb preview now']:.1f}x"
    )
    print(json.dumps({"cpu": cpu_name(), "median_ms": medians}))


if __name__ == "__main__":
    main()
