from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import TINY_INPUT_SIZE, textured_image

pytest.importorskip("torch")

from gcdtrav.schemas.anchors import default_anchor_set
from gcdtrav.service.commands.cli import main
from gcdtrav.service.engine import gcd


@pytest.fixture()
def images(tmp_path: Path) -> dict[str, Path]:
    folder = tmp_path / "in"
    folder.mkdir()
    good = folder / "scene.jpg"
    cv2.imwrite(str(good), textured_image(90, 140)[:, :, ::-1])
    png = folder / "other.png"
    cv2.imwrite(str(png), textured_image(50, 60, seed=3)[:, :, ::-1])
    garbage = folder / "garbage.jpg"
    garbage.write_bytes(b"\xff\xd8 this is no jpeg at all")
    empty = folder / "empty.png"
    empty.write_bytes(b"")
    return {"good": good, "png": png, "garbage": garbage, "empty": empty, "missing": folder / "missing.jpg"}


def test_infer_writes_maps_overlays_figure_and_raw(
    tmp_path: Path, tiny_model_dir: Path, images: dict[str, Path]
) -> None:
    out = tmp_path / "out"
    code = main(
        [
            "infer",
            str(images["good"]),
            "--out",
            str(out),
            "--model",
            str(tiny_model_dir),
            "--save-raw",
            "--probe",
            "10,20",
            "--probe",
            "130,80",
            "--figure",
        ]
    )
    assert code == 0
    folder = out / "scene"
    t16 = cv2.imread(str(folder / "T.png"), cv2.IMREAD_UNCHANGED)
    u16 = cv2.imread(str(folder / "U.png"), cv2.IMREAD_UNCHANGED)
    assert t16.dtype == np.uint16 and t16.shape == (90, 140) and u16.shape == (90, 140)
    for name in ("T_overlay.jpg", "U_overlay.jpg", "figure.png"):
        assert cv2.imread(str(folder / name)) is not None
    logits = np.load(folder / "logits.npy")
    t, u = np.load(folder / "T.npy"), np.load(folder / "U.npy")
    assert logits.dtype == np.float32 and logits.shape == (13, TINY_INPUT_SIZE, TINY_INPUT_SIZE)
    assert t.shape == u.shape == (TINY_INPUT_SIZE, TINY_INPUT_SIZE)
    anchors = default_anchor_set()
    expected_t, expected_u = gcd.mixture_mean_std(gcd.softmax_weights(logits), anchors.positions, anchors.widths)
    np.testing.assert_allclose(t, expected_t, atol=1e-6)
    np.testing.assert_allclose(u, expected_u, atol=1e-6)
    assert json.loads((folder / "anchors.json").read_text())["anchors"][0]["concept"] == "water"
    # The full-size PNG is the upsampled map, quantised to 1/65535.
    resized = cv2.resize(expected_t, (140, 90), interpolation=cv2.INTER_LINEAR)
    np.testing.assert_allclose(t16 / 65535.0, resized, atol=2 / 65535)


def test_bad_images_are_reported_and_the_rest_processed(
    tmp_path: Path, tiny_model_dir: Path, images: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    args = [str(images[k]) for k in ("garbage", "good", "empty", "missing", "png")]
    code = main(["infer", *args, "--out", str(out), "--model", str(tiny_model_dir)])
    assert code == 1
    assert not (out / "scene" / "figure.png").exists()  # the figure is opt-in
    err = capsys.readouterr().err
    assert f"{images['garbage']}: not a decodable image" in err
    assert f"{images['empty']}: empty payload" in err
    assert f"{images['missing']}: cannot read the file" in err
    assert "2 of 5 images written" in err
    assert (out / "scene" / "T.png").exists() and (out / "other" / "U.png").exists()


def test_invalid_anchor_file_is_one_clear_message(
    tmp_path: Path, tiny_model_dir: Path, images: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "anchors.yaml"
    bad.write_text("anchors:\n  - {concept: grass, position: 0.5}\n  - {concept: water, position: 0.02}\n")
    code = main(
        [
            "infer",
            str(images["good"]),
            "--out",
            str(tmp_path / "o"),
            "--model",
            str(tiny_model_dir),
            "--anchors",
            str(bad),
        ]
    )
    assert code == 2
    err = capsys.readouterr().err
    assert "anchors.yaml" in err and "sorted by position" in err
    assert "Traceback" not in err


def test_custom_anchors_and_methods(tmp_path: Path, tiny_model_dir: Path, images: dict[str, Path]) -> None:
    anchors = tmp_path / "anchors.json"
    anchors.write_text(
        json.dumps(
            {
                "anchors": [
                    {"concept": "puddle", "position": 0.0},
                    {"concept": "road", "position": 1.0, "width": 0.1},
                ]
            }
        )
    )
    for method in ("gcd", "argmax", "gaussian"):
        out = tmp_path / method
        assert (
            main(
                [
                    "infer",
                    str(images["png"]),
                    "--out",
                    str(out),
                    "--model",
                    str(tiny_model_dir),
                    "--anchors",
                    str(anchors),
                    "--method",
                    method,
                    "--save-raw",
                    "--no-figure",
                ]
            )
            == 0
        )
        assert np.load(out / "other" / "logits.npy").shape[0] == 2
        summary = json.loads((out / "other" / "summary.json").read_text())
        assert summary["method"] == method


def test_missing_model_exits_2_without_traceback(
    tmp_path: Path, images: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    code = main(["infer", str(images["good"]), "--out", str(tmp_path / "o"), "--model", str(tmp_path / "none")])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--model" in err[0] and "GCDTRAV_MODEL" in err[0]


def test_bad_probe_is_a_usage_error(tmp_path: Path, images: dict[str, Path]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["infer", str(images["good"]), "--out", str(tmp_path), "--probe", "left"])
    assert info.value.code == 2
