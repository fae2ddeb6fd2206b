"""`gcdtrav eval` on a synthetic GOOSE-layout dataset, with a backend whose logits the test sets."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from gcdtrav.schemas.anchors import Anchor, AnchorSet
from gcdtrav.schemas.config import Method
from gcdtrav.service.backends.base import BackendDescription
from gcdtrav.service.eval import metrics
from gcdtrav.service.eval.datasets import DatasetError, goose_class_names, load_dataset
from gcdtrav.service.eval.mapping import load_mapping

ANCHORS = AnchorSet(
    anchors=[
        Anchor(concept="water", position=0.0),
        Anchor(concept="grass", position=0.5),
        Anchor(concept="asphalt", position=1.0),
    ]
)
SKY, ASPHALT, WATER, LOW_GRASS, HEDGE, SNOW = 53, 23, 54, 50, 59, 2
H, W = 32, 48  # images; the fake backend's maps are 16 x 24 (one cell = 2 x 2 pixels)
DOMINANT = 200.0  # exp(-200) is 0 in float32: the weights are exactly one-hot


class FakeBackend:
    """Returns the logits the test set for each image (looked up by the image's content)."""

    model_id = "fake-backend"

    def __init__(self) -> None:
        self.by_image: dict[str, np.ndarray] = {}
        self.calls = 0

    def set(self, image: np.ndarray, logits: np.ndarray) -> None:
        self.by_image[hashlib.sha1(image.tobytes()).hexdigest()] = logits

    def describe(self) -> BackendDescription:
        return BackendDescription(self.model_id)

    def prepare(self, concepts):  # type: ignore[no-untyped-def]
        return tuple(concepts)

    def logits(self, image, prepared):  # type: ignore[no-untyped-def]
        self.calls += 1
        return self.by_image[hashlib.sha1(image.tobytes()).hexdigest()]


def one_hot_logits(index: int) -> np.ndarray:
    logits = np.zeros(3, np.float32)
    logits[index] = DOMINANT
    return logits


def write_goose(root: Path, backend: FakeBackend) -> None:
    """Two frames. a: sky on top, asphalt left (model: asphalt), water right (model: undecided).
    b: low grass (model: grass) with a hedge patch (model: water)."""
    images, labels = root / "images" / "val" / "seq1", root / "labels" / "val" / "seq1"
    images.mkdir(parents=True)
    labels.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for name in ("a", "b"):
        image = rng.integers(0, 255, size=(H, W, 3), dtype=np.uint8)
        cv2.imwrite(str(images / f"{name}_windshield_vis.png"), image[:, :, ::-1])
        ids = np.full((H, W), SKY, np.uint8)
        logits = np.zeros((3, H // 2, W // 2), np.float32)
        if name == "a":
            ids[8:, :24], ids[8:, 24:] = ASPHALT, WATER
            logits[:, 4:, :12] = one_hot_logits(2)[:, None, None]
            # water: all logits equal -> w = 1/3 each, T = 0.5, U = sqrt(1/6)
        else:
            ids[8:, :], ids[8:16, :24] = LOW_GRASS, HEDGE
            logits[:, 4:, :] = one_hot_logits(1)[:, None, None]
            logits[:, 4:8, :12] = one_hot_logits(0)[:, None, None]
        cv2.imwrite(str(labels / f"{name}_labelids.png"), ids)
        # A colour file whose colour would say "snow" for hedge pixels: must never be read.
        cv2.imwrite(str(labels / f"{name}_color.png"), np.full((H, W, 3), 200, np.uint8))
        backend.set(image, logits)


@pytest.fixture()
def goose(tmp_path: Path) -> tuple[Path, FakeBackend]:
    backend = FakeBackend()
    write_goose(tmp_path / "goose", backend)
    return tmp_path / "goose", backend


def run(root: Path, backend: FakeBackend, out: Path, **kw: object) -> dict:
    from gcdtrav.service.eval.run import EvalOptions, run_eval

    dataset = load_dataset("goose", root, "val")
    table = load_mapping("goose", dataset.class_names)
    options = EvalOptions(out_dir=out, grid=4, **kw)  # type: ignore[arg-type]
    return run_eval(backend, ANCHORS, dataset, table, options)  # type: ignore[arg-type]


def test_metrics_by_hand_on_the_synthetic_set(goose: tuple[Path, FakeBackend], tmp_path: Path) -> None:
    root, backend = goose
    report = run(root, backend, tmp_path / "out")
    # Grid 4 -> rows 2, 6, ..., 30 and columns 2, ..., 46; rows 2 and 6 are sky (ignored): 6 x 12 per image.
    # a: 36 asphalt (T 1.0, gt 0.98, err 0.02), 36 water (T 0.5, gt 0.02, err 0.48)
    # b: 12 hedge (rows 10, 14, cols < 24; T 0.0, gt 0.05, err 0.05), 60 low grass (T 0.5, gt 0.5, err 0)
    gcd = report["overall"]["gcd"]
    assert gcd["pixels"] == 144
    assert gcd["mae"] == pytest.approx((36 * 0.02 + 36 * 0.48 + 12 * 0.05) / 144, abs=1e-6)
    assert gcd["rmse"] == pytest.approx(np.sqrt((36 * 0.02**2 + 36 * 0.48**2 + 12 * 0.05**2) / 144), abs=1e-6)
    per_class = report["per_class"]["gcd"]
    assert per_class["water"]["mae"] == pytest.approx(0.48, abs=1e-6)
    assert per_class["water"]["U_median"] == pytest.approx(np.sqrt(1 / 6), abs=1e-6)
    assert per_class["asphalt"]["pixels"] == 36 and per_class["hedge"]["pixels"] == 12
    assert per_class["hedge"]["ground_truth"] == pytest.approx(0.05)
    assert "snow" not in per_class and "sky" not in per_class
    # Only water is wrong by more than 0.25 and only water has U > 0: U separates errors perfectly.
    assert gcd["auroc_u_error_gt_0.25"] == pytest.approx(1.0)
    # Spearman by hand: U ranks (108 zeros -> 54.5, 36 water -> 126.5); |err| ranks (60 grass -> 30.5,
    # 36 asphalt -> 78.5, 12 hedge -> 102.5, 36 water -> 126.5).
    rank_u = np.array([54.5] * 108 + [126.5] * 36)
    rank_e = np.array([30.5] * 60 + [78.5] * 36 + [102.5] * 12 + [126.5] * 36)
    assert gcd["spearman_u_abs_error"] == pytest.approx(np.corrcoef(rank_u, rank_e)[0, 1], abs=1e-9)
    # argmax: the undecided water patches take the first anchor (water, 0.0): err 0.02, U = 2/3.
    argmax = report["overall"]["argmax"]
    assert argmax["mae"] == pytest.approx((36 * 0.02 + 36 * 0.02 + 12 * 0.05) / 144, abs=1e-6)
    assert np.isnan(argmax["auroc_u_error_gt_0.25"])  # no pixel is wrong by more than 0.25
    assert report["images"] == 2 and report["failures"] == []
    out = tmp_path / "out"
    summary = (out / "summary.md").read_text()
    assert "| gcd | 144 | 0.1292 |" in summary
    saved = json.loads((out / "metrics.json").read_text())
    assert saved["overall"]["gcd"]["mae"] == pytest.approx(gcd["mae"])
    assert "water" in (out / "per_class.csv").read_text()
    for figure in ("fig_class_boxplots_gcd.png", "fig_error_by_method.png", "fig_sparsification.png"):
        assert cv2.imread(str(out / figure)) is not None


def test_interrupted_run_resumes_from_the_cache(goose: tuple[Path, FakeBackend], tmp_path: Path) -> None:
    root, backend = goose
    first = run(root, backend, tmp_path / "out", limit=1, figures=False)
    assert backend.calls == 1 and first["overall"]["gcd"]["pixels"] == 72
    second = run(root, backend, tmp_path / "out", figures=False)
    assert backend.calls == 2  # only the image not yet cached was computed
    assert second["overall"]["gcd"]["pixels"] == 144
    third = run(root, backend, tmp_path / "out", figures=False, methods=(Method.GCD,))
    assert backend.calls == 4 and list(third["overall"]) == ["gcd"]  # other settings: a fresh cache


def test_bad_image_is_reported_and_the_rest_evaluated(goose: tuple[Path, FakeBackend], tmp_path: Path) -> None:
    root, backend = goose
    (root / "images" / "val" / "seq1" / "b_windshield_vis.png").write_bytes(b"not a png")
    report = run(root, backend, tmp_path / "out", figures=False)
    assert report["images"] == 1 and len(report["failures"]) == 1 and "b_windshield_vis" in report["failures"][0]


def test_loader_and_mapping_errors(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="images/val/ and labels/val/"):
        load_dataset("goose", tmp_path, "val")
    names = goose_class_names()
    assert names[2] == "snow" and names[59] == "hedge" and len(names) == 64
    bad = tmp_path / "m.yaml"
    bad.write_text("classes:\n  asfalt: 0.9\n")
    with pytest.raises(DatasetError, match=r"'asfalt' is not a class.*has no value"):
        load_mapping(bad, names)
    table = load_mapping("goose", names)
    assert table[ASPHALT] == pytest.approx(0.98) and np.isnan(table[SKY]) and table[WATER] == pytest.approx(0.02)


def test_rugd_and_generic_loaders(tmp_path: Path) -> None:
    rugd = tmp_path / "rugd"
    (rugd / "RUGD_frames-with-annotations" / "creek").mkdir(parents=True)
    (rugd / "RUGD_annotations" / "creek").mkdir(parents=True)
    (rugd / "RUGD_annotations" / "RUGD_annotation-colormap.txt").write_text("0 void 0 0 0\n1 dirt 108 64 20\n")
    cv2.imwrite(str(rugd / "RUGD_frames-with-annotations" / "creek" / "creek_1.png"), np.zeros((4, 4, 3), np.uint8))
    colour = np.zeros((4, 4, 3), np.uint8)
    colour[:2] = (20, 64, 108)  # BGR of dirt
    colour[3, 3] = (1, 2, 3)  # not in the colormap: ignored
    cv2.imwrite(str(rugd / "RUGD_annotations" / "creek" / "creek_1.png"), colour)
    dataset = load_dataset("rugd", rugd, None)
    ids = dataset.samples[0].read_labels()
    assert ids[0, 0] == 1 and ids[2, 0] == 0 and ids[3, 3] == -1
    generic = tmp_path / "generic"
    (generic / "images").mkdir(parents=True)
    (generic / "masks").mkdir()
    (generic / "classes.csv").write_text("id,name\n0,road\n1,pond\n")
    cv2.imwrite(str(generic / "images" / "x.jpg"), np.zeros((4, 4, 3), np.uint8))
    cv2.imwrite(str(generic / "masks" / "x.png"), np.ones((4, 4), np.uint8))
    dataset = load_dataset("generic", generic, None)
    assert dataset.class_names == {0: "road", 1: "pond"} and dataset.samples[0].read_labels()[0, 0] == 1


def dirt_annotation() -> np.ndarray:
    colour = np.zeros((4, 4, 3), np.uint8)
    colour[:2] = (20, 64, 108)  # BGR of dirt
    return colour


def test_rugd_flat_sample_layout(tmp_path: Path) -> None:
    """The layout RUGD samples are often shared in: images/ and annotations/, the colormap beside them."""
    flat = tmp_path / "rugd-sample"
    (flat / "images").mkdir(parents=True)
    (flat / "annotations").mkdir()
    (flat / "RUGD_annotation-colormap.txt").write_text("0 void 0 0 0\n1 dirt 108 64 20\n")
    for name in ("creek_00001", "creek_00002", "trail-3_00001", "park-1_00001"):
        cv2.imwrite(str(flat / "images" / f"{name}.jpg"), np.zeros((4, 4, 3), np.uint8))
        if name != "park-1_00001":  # a frame without an annotation is skipped
            cv2.imwrite(str(flat / "annotations" / f"{name}.png"), dirt_annotation())
    dataset = load_dataset("rugd", flat, None)
    assert [s.name for s in dataset.samples] == ["creek_00001", "creek_00002", "trail-3_00001"]
    assert dataset.class_names == {0: "void", 1: "dirt"} and dataset.samples[0].read_labels()[0, 0] == 1
    assert [s.name for s in load_dataset("rugd", flat, "trail-3").samples] == ["trail-3_00001"]
    (flat / "RUGD_annotation-colormap.txt").rename(flat / "annotations" / "RUGD_annotation-colormap.txt")
    assert len(load_dataset("rugd", flat, "creek").samples) == 2  # the colormap in annotations/ is found too
    (flat / "annotations" / "RUGD_annotation-colormap.txt").unlink()
    with pytest.raises(DatasetError, match=r"no RUGD_annotation-colormap\.txt in annotations/ or in the root"):
        load_dataset("rugd", flat, None)


def test_rugd_without_either_layout_names_both(tmp_path: Path) -> None:
    (tmp_path / "images").mkdir()
    with pytest.raises(DatasetError, match=r"RUGD_frames-with-annotations.*or the flat one, images/ and annotations/"):
        load_dataset("rugd", tmp_path, None)
    (tmp_path / "annotations").mkdir()
    (tmp_path / "RUGD_annotation-colormap.txt").write_text("0 void 0 0 0\n")
    with pytest.raises(DatasetError, match="no frame in images/ with an annotation of the same name"):
        load_dataset("rugd", tmp_path, None)


def test_metric_functions_by_hand() -> None:
    assert metrics.average_ranks(np.array([3.0, 1.0, 3.0, 2.0])).tolist() == [3.5, 1.0, 3.5, 2.0]
    assert metrics.spearman(np.array([1.0, 2, 3, 4]), np.array([10.0, 20, 30, 40])) == pytest.approx(1.0)
    assert metrics.spearman(np.array([1.0, 2, 3, 4]), np.array([4.0, 3, 2, 1])) == pytest.approx(-1.0)
    # AUROC: positives scored (0.9, 0.4), negatives (0.5, 0.1): 3 of 4 pairs ordered right.
    assert metrics.auroc(np.array([0.9, 0.4, 0.5, 0.1]), np.array([True, True, False, False])) == pytest.approx(0.75)
    assert metrics.auroc(np.array([0.5, 0.5]), np.array([True, False])) == pytest.approx(0.5)
    error = np.array([0.4, 0.3, 0.2, 0.1])
    fractions, curve = metrics.sparsification_curve(error, np.array([4.0, 3, 2, 1]), steps=4)
    assert fractions.tolist() == [0, 0.25, 0.5, 0.75]
    np.testing.assert_allclose(curve, [0.25, 0.2, 0.15, 0.1])
    assert metrics.ause(error, error)["ause"] == pytest.approx(0.0)  # U ranks errors perfectly
    worst = metrics.ause(error, -error)  # U ranks them backwards
    assert worst["ause"] > 0.05 and worst["ause_relative"] == pytest.approx(worst["ause"] / 0.25)
