"""Labelled image datasets: GOOSE 2D, RUGD, and a generic images + id masks layout.

Each yields samples of (image path, a function that reads the label ids, a name). Label ids are class
indices into the dataset's class list; traversability values come from a mapping file (``mapping.py``).
"""

from __future__ import annotations

import csv
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from importlib import resources
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


class DatasetError(ValueError):
    """A dataset folder that doesn't have the expected layout; the message says what was looked for."""


@dataclass(frozen=True)
class Sample:
    name: str  # relative, unique within the dataset: the cache key
    image_path: Path
    read_labels: Callable[[], NDArray[np.int32]]


@dataclass(frozen=True)
class Dataset:
    kind: str
    class_names: dict[int, str]
    samples: list[Sample]


def _read_id_png(path: Path) -> NDArray[np.int32]:
    ids = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if ids is None:
        raise DatasetError(f"{path}: not a readable label image")
    if ids.ndim == 3:  # a 3-channel copy of an id image: all channels hold the id
        ids = ids[:, :, 0]
    return ids.astype(np.int32)


def goose_class_names() -> dict[int, str]:
    text = resources.files("gcdtrav.service.eval").joinpath("data/goose_classes.csv").read_text("utf-8")
    return {int(row["label_key"]): row["class_name"] for row in csv.DictReader(text.splitlines())}


def load_goose(root: Path, split: str) -> Dataset:
    """GOOSE 2D: ``images/{split}/<seq>/<name>_<camera>.png`` with ``labels/{split}/<seq>/<name>_labelids.png``.

    Labels are read from the ``*_labelids.png`` files (pixel = class id 0-63), never from the colour
    images: snow (2) and hedge (59) share a colour.
    """
    label_root, image_root = root / "labels" / split, root / "images" / split
    if not label_root.is_dir() or not image_root.is_dir():
        raise DatasetError(f"{root}: expected GOOSE folders images/{split}/ and labels/{split}/")
    samples = []
    for label_path in sorted(label_root.rglob("*_labelids.png")):
        relative = label_path.parent.relative_to(label_root)
        prefix = label_path.name[: -len("_labelids.png")]
        candidates = sorted(
            p for p in (image_root / relative).glob(f"{prefix}_*") if p.suffix.lower() in IMAGE_SUFFIXES
        )
        if not candidates:
            raise DatasetError(f"{label_path}: no image {image_root / relative / prefix}_*.png for this label file")
        samples.append(Sample(str(relative / prefix), candidates[0], partial(_read_id_png, label_path)))
    if not samples:
        raise DatasetError(f"{label_root}: no *_labelids.png files")
    return Dataset("goose", goose_class_names(), samples)


def read_rugd_colormap(path: Path) -> tuple[dict[int, str], dict[tuple[int, int, int], int]]:
    """``RUGD_annotation-colormap.txt``: lines 'id name r g b'."""
    names: dict[int, str] = {}
    colours: dict[tuple[int, int, int], int] = {}
    for number, line in enumerate(path.read_text("utf-8").splitlines(), 1):
        parts = line.split()
        if not parts:
            continue
        if len(parts) != 5:
            raise DatasetError(f"{path}:{number}: expected 'id name r g b', got '{line}'")
        index = int(parts[0])
        names[index] = parts[1]
        colours[(int(parts[2]), int(parts[3]), int(parts[4]))] = index
    return names, colours


def _rugd_ids(path: Path, colours: dict[tuple[int, int, int], int]) -> NDArray[np.int32]:
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise DatasetError(f"{path}: not a readable annotation image")
    channels = bgr.astype(np.int32)
    packed = (channels[:, :, 2] << 16) | (channels[:, :, 1] << 8) | channels[:, :, 0]
    ids = np.full(packed.shape, -1, np.int32)  # colours not in the map stay -1 (ignored)
    for (r, g, b), index in colours.items():
        ids[packed == (r << 16 | g << 8 | b)] = index
    return ids


RUGD_COLORMAP = "RUGD_annotation-colormap.txt"
RUGD_LAYOUTS = (("RUGD_frames-with-annotations", "RUGD_annotations"), ("images", "annotations"))


def _rugd_folders(root: Path) -> tuple[Path, Path, Path]:
    """(frames, annotations, colormap) of the official layout or of the flat one of the common samples."""
    for frames_name, annotations_name in RUGD_LAYOUTS:
        frames, annotations = root / frames_name, root / annotations_name
        if frames.is_dir() and annotations.is_dir():
            candidates = (annotations / RUGD_COLORMAP, root / RUGD_COLORMAP)
            colormap = next((path for path in candidates if path.is_file()), None)
            if colormap is None:
                raise DatasetError(f"{root}: no {RUGD_COLORMAP} in {annotations_name}/ or in the root folder")
            return frames, annotations, colormap
    raise DatasetError(
        f"{root}: expected RUGD's layout, RUGD_frames-with-annotations/<seq>/*.png and RUGD_annotations/<seq>/*.png, "
        f"or the flat one, images/ and annotations/ (same names, annotations as PNG); with {RUGD_COLORMAP}"
    )


def _rugd_sequence(relative: Path) -> str:
    """The sequence a frame belongs to: its folder, or in a flat folder its name before the frame number
    (``creek_00001`` -> ``creek``)."""
    return relative.parts[0] if len(relative.parts) > 1 else relative.stem.rsplit("_", 1)[0]


def load_rugd(root: Path, split: str | None) -> Dataset:
    """RUGD, in its official layout: ``RUGD_frames-with-annotations/<seq>/*.png``, colour annotations
    ``RUGD_annotations/<seq>/*.png`` and ``RUGD_annotations/RUGD_annotation-colormap.txt``; or flat, as
    samples of it are often shared: ``images/*.(png|jpg)``, ``annotations/*.png`` and the colormap in
    ``annotations/`` or the root. ``split`` is a comma list of sequences, or all."""
    frames, annotations, colormap = _rugd_folders(root)
    names, colours = read_rugd_colormap(colormap)
    wanted = None if split in (None, "", "all", "val") else set(split.split(","))
    samples = []
    for image_path in sorted(p for p in frames.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()):
        relative = image_path.relative_to(frames)
        if wanted is not None and _rugd_sequence(relative) not in wanted:
            continue
        annotation = annotations / relative.with_suffix(".png")
        if annotation.is_file():
            name = relative.with_suffix("").as_posix()
            samples.append(Sample(name, image_path, partial(_rugd_ids, annotation, colours)))
    if not samples:
        raise DatasetError(
            f"{root}: no frame in {frames.name}/ with an annotation of the same name in {annotations.name}/"
        )
    return Dataset("rugd", names, samples)


def load_generic(root: Path) -> Dataset:
    """``images/<name>.(png|jpg)``, ``masks/<name>.png`` (pixel = class id), ``classes.csv`` (id,name)."""
    class_file = root / "classes.csv"
    if not class_file.is_file() or not (root / "images").is_dir() or not (root / "masks").is_dir():
        raise DatasetError(f"{root}: expected images/, masks/ and classes.csv (id,name)")
    names: dict[int, str] = {}
    for row in csv.reader(class_file.read_text("utf-8").splitlines()):
        if row and row[0].strip().isdigit():
            names[int(row[0])] = row[1].strip()
    samples = []
    for image_path in sorted(p for p in (root / "images").iterdir() if p.suffix.lower() in IMAGE_SUFFIXES):
        mask = root / "masks" / f"{image_path.stem}.png"
        if mask.is_file():
            samples.append(Sample(image_path.stem, image_path, partial(_read_id_png, mask)))
    if not samples:
        raise DatasetError(f"{root}: no image with a mask of the same name")
    return Dataset("generic", names, samples)


def load_dataset(kind: str, root: Path, split: str | None) -> Dataset:
    if kind == "goose":
        return load_goose(root, split or "val")
    if kind == "rugd":
        return load_rugd(root, split)
    if kind == "generic":
        return load_generic(root)
    raise DatasetError(f"unknown dataset kind '{kind}' (goose, rugd, generic)")
