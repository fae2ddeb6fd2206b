"""`gcdtrav infer --figure --probe X,Y` outside the image: exit 2, one line naming the image and its size
(it was clamped to the border, silently)."""

from __future__ import annotations

from pathlib import Path

import cv2
import pytest
from conftest import textured_image

pytest.importorskip("torch")

from gcdtrav.service.commands.cli import main


@pytest.mark.parametrize("probe", ["140,10", "10,90", "-1,5"])
def test_a_probe_outside_the_image_is_a_usage_error_naming_its_size(
    tmp_path: Path, tiny_model_dir: Path, capsys: pytest.CaptureFixture[str], probe: str
) -> None:
    image = tmp_path / "scene.png"
    cv2.imwrite(str(image), textured_image(90, 140))
    out = tmp_path / "out"
    args = ["infer", str(image), "--out", str(out), "--model", str(tiny_model_dir), "--figure", f"--probe={probe}"]
    assert main([*args, "--probe", "139,89"]) == 2
    err = capsys.readouterr().err  # the model's loading progress, then the error
    assert err.strip().splitlines()[-1] == (
        f"gcdtrav infer: --probe {probe} is outside {image} (140x90 pixels: x 0..139, y 0..89)"
    )
    assert "Traceback" not in err
    assert not (out / "scene" / "figure.png").exists()


def test_the_last_pixel_is_inside(tmp_path: Path, tiny_model_dir: Path) -> None:
    image = tmp_path / "scene.png"
    cv2.imwrite(str(image), textured_image(90, 140))
    args = ["infer", str(image), "--out", str(tmp_path / "out"), "--model", str(tiny_model_dir), "--figure"]
    assert main([*args, "--probe", "139,89", "--probe", "0,0"]) == 0
    assert (tmp_path / "out" / "scene" / "figure.png").exists()


def test_a_probe_without_figure_prints_its_answer_and_outside_exits_2(
    tmp_path: Path, tiny_model_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The README's headline `gcdtrav infer ... --probe 320,400`: the answer is printed, pixel and patch named;
    outside the image it is a usage error as --help says, with or without --figure."""
    image = tmp_path / "scene.png"
    cv2.imwrite(str(image), textured_image(480, 640))
    args = ["infer", str(image), "--out", str(tmp_path / "out"), "--model", str(tiny_model_dir)]
    assert main([*args, "--probe", "320,400"]) == 0
    out = capsys.readouterr().out
    patch = f"patch (row i={int(400 * 96 / 480)}, column j={int(320 * 96 / 640)})"  # the tiny model's 96x96 maps
    assert out.startswith(f"{image} pixel (x=320, y=400) in {patch} anchors=")
    assert "T (mean) =" in out and "CVaR(alpha=0.1)" in out and "asphalt @ 0.98" in out
    assert not (tmp_path / "out" / "scene" / "figure.png").exists()
    assert main([*args, "--probe", "640,10"]) == 2
    assert "--probe 640,10 is outside" in capsys.readouterr().err


def test_a_probe_outside_a_later_image_stops_before_any_inference(
    tmp_path: Path, tiny_model_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    first, later = tmp_path / "first.png", tmp_path / "later.png"
    cv2.imwrite(str(first), textured_image(480, 640))
    cv2.imwrite(str(later), textured_image(90, 140))
    out = tmp_path / "out"
    args = ["infer", str(first), str(later), "--out", str(out), "--model", str(tiny_model_dir)]
    assert main([*args, "--probe", "320,400"]) == 2
    assert f"--probe 320,400 is outside {later}" in capsys.readouterr().err
    assert not (out / "first").exists()  # checked before the first image's inference, not after


def test_infer_into_a_closed_pipe_writes_every_image_without_a_traceback(tmp_path: Path, tiny_model_dir: Path) -> None:
    """`gcdtrav infer ... --probe X,Y | head`: the reader goes, the run goes on quietly."""
    import subprocess
    import sys

    images = [tmp_path / f"img{i}.png" for i in range(3)]
    for image in images:
        cv2.imwrite(str(image), textured_image(90, 140))
    out = tmp_path / "out"
    args = ["infer", *map(str, images), "--out", str(out), "--model", str(tiny_model_dir), "--probe", "10,10"]
    code = f"import sys; from gcdtrav.service.commands.cli import main; sys.exit(main({args!r}))"
    process = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert process.stdout is not None and process.stderr is not None
    process.stdout.close()  # head exited before the first answer
    err = process.stderr.read()
    assert process.wait(timeout=120) == 0, err
    assert "Traceback" not in err and "BrokenPipe" not in err, err
    assert all((out / image.stem / "summary.json").is_file() for image in images)
