"""`gcdtrav eval --fit-anchors`: the experience fitter on label-derived traversability."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from gcdtrav.client.commands.experience import proposal_lines
from gcdtrav.schemas.anchors import Anchor, AnchorSet, anchor_diff
from gcdtrav.service.backends.base import BackendDescription
from gcdtrav.service.eval.datasets import load_dataset
from gcdtrav.service.eval.mapping import load_mapping
from gcdtrav.service.experience.dataset_fit import PROPOSED_FILE, fit_on_dataset
from gcdtrav.service.experience.fitter import FitOptions

ROOT = Path(__file__).resolve().parents[3]
START = AnchorSet(
    anchors=[
        Anchor(concept="water", position=0.3),
        Anchor(concept="grass", position=0.5),
        Anchor(concept="asphalt", position=0.6),
    ]
)
COLOURS = {"water": (0, 0, 255), "grass": (0, 255, 0), "asphalt": (128, 128, 128)}
LABELS = {"water": (1, 0.02), "grass": (2, 0.7), "asphalt": (3, 0.98)}


class ColourBackend:
    """Logits that name the concept whose colour a pixel has (softmax weight 0.99 on it)."""

    model_id = "colour"

    def describe(self) -> BackendDescription:
        return BackendDescription(self.model_id)

    def prepare(self, concepts):  # type: ignore[no-untyped-def]
        return list(concepts)

    def logits(self, image, prepared):  # type: ignore[no-untyped-def]
        logits = np.zeros((len(prepared), *image.shape[:2]), np.float32)
        for k, concept in enumerate(prepared):
            logits[k][np.all(image == COLOURS[concept], axis=2)] = 6.0
        return logits


def write_generic(root: Path) -> None:
    (root / "images").mkdir(parents=True)
    (root / "masks").mkdir()
    (root / "classes.csv").write_text("0,sky\n" + "".join(f"{i},{n}\n" for n, (i, _) in LABELS.items()))
    (root / "mapping.yaml").write_text(
        "classes:\n  sky: ignore\n" + "".join(f"  {n}: {v}\n" for n, (_, v) in LABELS.items())
    )
    rng = np.random.default_rng(0)
    for frame in range(6):
        image = np.zeros((32, 48, 3), np.uint8)
        ids = np.zeros((32, 48), np.uint8)
        for band, name in enumerate(rng.permutation(list(LABELS))):
            image[8 + 8 * band : 16 + 8 * band] = COLOURS[name]
            ids[8 + 8 * band : 16 + 8 * band] = LABELS[name][0]
        cv2.imwrite(str(root / "images" / f"f{frame}.png"), image[:, :, ::-1])
        cv2.imwrite(str(root / "masks" / f"f{frame}.png"), ids)


def test_the_fit_recovers_the_label_values_and_writes_a_set_anchors_set_accepts(tmp_path: Path) -> None:
    write_generic(tmp_path / "data")
    dataset = load_dataset("generic", tmp_path / "data", None)
    table = load_mapping(str(tmp_path / "data" / "mapping.yaml"), dataset.class_names)
    run = fit_on_dataset(ColourBackend(), START, dataset, table, tmp_path / "out", FitOptions(min_pairs_per_anchor=0))
    proposed = AnchorSet.load(tmp_path / "out" / PROPOSED_FILE)
    assert proposed == run.proposal.proposed
    fitted = dict(zip(proposed.concepts, proposed.positions, strict=True))
    assert fitted == pytest.approx({n: v for n, (_, v) in LABELS.items()}, abs=0.01)
    p = run.proposal
    assert p.train_pairs + p.held_out_pairs == 6 * (3 * 8 // 8) * (48 // 8)  # 3 bands x 6 columns, sky ignored
    assert p.after.mae is not None and p.before.mae is not None and p.after.mae < p.before.mae / 10
    assert p.diff == anchor_diff(START, proposed)
    text = "\n".join(proposal_lines(p))  # the text `gcdtrav anchors propose` prints
    assert "~ water @ 0.30 -> 0.02" in text and f"graded on the {p.held_out_pairs} later ones" in text
    assert p.verdict is not None and p.verdict.verdict == "better" and not p.verdict.enough_pairs  # a tiny set
    assert text.endswith(f"; {p.held_out_pairs} held-out pairs, fewer than the 200 a verdict needs")
    assert json.loads((tmp_path / "out" / "proposal.json").read_text())["proposed_version"] == proposed.version


def test_the_cli_on_synthetic_goose_with_the_tiny_model(tmp_path: Path, tiny_model_dir: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    subprocess.run(
        [sys.executable, str(ROOT / "examples" / "make_synthetic_goose.py"), str(tmp_path / "goose"), "--frames", "4"],
        check=True,
        capture_output=True,
    )
    from gcdtrav.service.commands.cli import main

    code = main(
        ["eval", "--dataset", "goose", "--root", str(tmp_path / "goose"), "--model", str(tiny_model_dir),
         "--precision", "fp32", "--grid", "16", "--out", str(tmp_path / "out"), "--fit-anchors"]
    )  # fmt: skip
    assert code == 0
    proposed = AnchorSet.load(tmp_path / "out" / PROPOSED_FILE)  # what `gcdtrav anchors set` reads
    printed = capsys.readouterr().out.splitlines()
    assert printed[-3].startswith("verdict: ") and printed[-1].startswith(f"proposed set: {tmp_path / 'out'}")
    assert "(not recommended: " in printed[-1] or "(judged better)" in printed[-1]
    report = json.loads((tmp_path / "out" / "proposal.json").read_text())
    assert report["held_out_pairs"] > 0 and report["train_pairs"] > report["held_out_pairs"]
    assert sorted(proposed.concepts) == sorted(AnchorSet.model_validate(report["current"]).concepts)
    assert not (tmp_path / "out" / "metrics.json").exists()  # fitting, not the evaluation
