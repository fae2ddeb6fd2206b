"""`gcdtrav infer`: images on disk to T/U maps, overlays and context-distribution figures."""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import cv2
import numpy as np
from gcdtrav.client.commands.density_plot import describe
from gcdtrav.schemas.images import ImageDecodeError, decode_image, quantize_map, resize_map
from gcdtrav.schemas.settings import RiskSettings
from gcdtrav.service.commands import figures as viz
from gcdtrav.service.pipeline import FrameResult, Pipeline
from gcdtrav.service.runtime.queries import RiskLevels, distribution_of, with_risk
from numpy.typing import NDArray


@dataclass(frozen=True)
class InferOptions:
    out_dir: Path
    probes: Sequence[tuple[int, int]] = ()
    save_raw: bool = False
    figure: bool = True


class ProbeOutsideImage(ValueError):
    """A --probe pixel the image does not have: a usage error, not something to clamp."""


def check_probes(probes: Sequence[tuple[int, int]], path: Path, width: int, height: int) -> None:
    for x, y in probes:
        if not (0 <= x < width and 0 <= y < height):
            raise ProbeOutsideImage(
                f"--probe {x},{y} is outside {path} ({width}x{height} pixels: x 0..{width - 1}, y 0..{height - 1})"
            )


def read_image(path: Path) -> NDArray[np.uint8]:
    try:
        data = path.read_bytes()
    except OSError as err:
        raise ImageDecodeError(f"cannot read the file ({err.strerror or err})") from None
    return decode_image(data)


def default_probes(u: NDArray[np.float32], height: int, width: int) -> list[tuple[int, int]]:
    """Without --probe: the most certain, the median and the most ambiguous pixel of U."""
    order = np.argsort(u, axis=None)
    picks = [order[0], order[len(order) // 2], order[-1]]
    scale_y, scale_x = height / u.shape[0], width / u.shape[1]
    return [(int((i % u.shape[1] + 0.5) * scale_x), int((i // u.shape[1] + 0.5) * scale_y)) for i in picks]


def patches_of(
    result: FrameResult, probes: Sequence[tuple[int, int]], height: int, width: int
) -> list[tuple[int, int]]:
    """(row i, column j) of the patch covering each probe pixel (x, y), as the service's patch query maps it."""
    h, w = result.maps.weights.shape[1:]
    return [(min(int(y * h / height), h - 1), min(int(x * w / width), w - 1)) for x, y in probes]


def weights_at(result: FrameResult, probes: Sequence[tuple[int, int]], height: int, width: int) -> NDArray[np.float32]:
    """(n, len(probes)): each probe pixel's anchor weights, from the patch that covers it."""
    rows, cols = zip(*patches_of(result, probes, height, width), strict=True) if probes else ((), ())
    return result.maps.weights[:, list(rows), list(cols)]


def probe_answers(
    name: str, result: FrameResult, probes: Sequence[tuple[int, int]], height: int, width: int
) -> list[str]:
    """Each --probe pixel's context distribution, as `gcdtrav probe` prints it (risk at the default levels)."""
    weights = weights_at(result, probes, height, width)
    levels = RiskLevels(RiskSettings().alpha, RiskSettings().tau)
    answers = []
    for k, (pixel, patch) in enumerate(zip(probes, patches_of(result, probes, height, width), strict=True)):
        column = np.asarray(weights[:, k], np.float32)
        d = distribution_of(column, result.anchors, name, seq=None, stamp=0.0, patch=patch)
        answers.append(describe(with_risk(d, column, result.anchors, levels), (float(pixel[0]), float(pixel[1]))))
    return answers


def write_outputs(stem_dir: Path, image: NDArray[np.uint8], result: FrameResult, options: InferOptions) -> None:
    stem_dir.mkdir(parents=True, exist_ok=True)
    height, width = image.shape[:2]
    t = resize_map(result.maps.traversability, width, height)
    u = resize_map(result.maps.uncertainty, width, height)
    cv2.imwrite(str(stem_dir / "T.png"), quantize_map(t))
    cv2.imwrite(str(stem_dir / "U.png"), quantize_map(u))
    for name, colours in (
        ("T_overlay.jpg", viz.colorize_traversability(t)),
        ("U_overlay.jpg", viz.colorize_uncertainty(u)),
    ):
        cv2.imwrite(str(stem_dir / name), cv2.cvtColor(viz.overlay(image, colours), cv2.COLOR_RGB2BGR))
    if options.save_raw:
        np.save(stem_dir / "logits.npy", result.logits.astype(np.float32))
        np.save(stem_dir / "T.npy", result.maps.traversability)
        np.save(stem_dir / "U.npy", result.maps.uncertainty)
        (stem_dir / "anchors.json").write_text(result.anchors.to_json() + "\n", "utf-8")
    if options.figure:
        probes = list(options.probes) or default_probes(result.maps.uncertainty, height, width)
        viz.save_context_figure(
            stem_dir / "figure.png",
            image,
            t,
            u,
            weights_at(result, probes, height, width),
            probes,
            result.anchors,
            title=stem_dir.name,
        )


def output_dirs(images: Sequence[Path], out_dir: Path) -> list[Path]:
    """One folder per image, named by its stem; repeated stems get a numeric suffix."""
    seen: dict[str, int] = {}
    dirs = []
    for path in images:
        count = seen.get(path.stem, 0)
        seen[path.stem] = count + 1
        dirs.append(out_dir / (path.stem if count == 0 else f"{path.stem}_{count}"))
    return dirs


def check_probes_first(probes: Sequence[tuple[int, int]], images: Sequence[Path]) -> None:
    """Every --probe against every image before any inference: a usage error is not found after an hour's work.
    Images are decoded for it (their decoded size is the one that counts: EXIF orientation); unreadable ones are
    left to the run, which reports them."""
    for path in images if probes else ():
        try:
            image = read_image(path)
        except ImageDecodeError:
            continue
        check_probes(probes, path, image.shape[1], image.shape[0])


class ClosedPipeWriter:
    """Writes to a stream until its reader goes (``gcdtrav infer ... | head``); then nothing more, quietly:
    the images are still processed and written, as the command line asked."""

    def __init__(self, stream: TextIO) -> None:
        self.stream, self.closed = stream, False

    def write(self, text: str) -> None:
        if self.closed:
            return
        try:
            self.stream.write(text)
            self.stream.flush()
        except BrokenPipeError:
            self.closed = True
            # What is still buffered would fail again at exit ("Exception ignored"): point the fd at devnull.
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, self.stream.fileno())
            os.close(devnull)


def run_infer(pipeline: Pipeline, images: Sequence[Path], options: InferOptions) -> int:
    """Process every image; a bad one is reported and skipped. Returns the number of failures.

    Raises ProbeOutsideImage (before any inference) for a --probe pixel outside an image.
    """
    from tqdm import tqdm

    check_probes_first(options.probes, images)
    answers = ClosedPipeWriter(sys.stdout)
    failures = 0
    targets = list(zip(images, output_dirs(images, options.out_dir), strict=True))
    progress = tqdm(targets, desc="infer", unit="img", disable=len(targets) < 2, file=sys.stderr)
    for path, stem_dir in progress:
        try:
            image = read_image(path)
        except ImageDecodeError as err:
            failures += 1
            progress.write(f"error: {path}: {err}", file=sys.stderr)
            continue
        check_probes(options.probes, path, image.shape[1], image.shape[0])
        result = pipeline.process(image)
        write_outputs(stem_dir, image, result, options)
        for answer in probe_answers(str(path), result, options.probes, *image.shape[:2]):
            with progress.external_write_mode(file=sys.stdout):
                answers.write(answer + "\n\n")
        summary = {
            "image": str(path),
            "size": [image.shape[1], image.shape[0]],
            "map_shape": list(result.maps.traversability.shape),
            "anchor_set_version": result.anchors.version,
            "method": pipeline.settings.method.value,
            "inference_ms": round(result.inference_ms, 1),
            "T_mean": float(result.maps.traversability.mean()),
            "U_mean": float(result.maps.uncertainty.mean()),
        }
        (stem_dir / "summary.json").write_text(json.dumps(summary, indent=2) + "\n", "utf-8")
    return failures
