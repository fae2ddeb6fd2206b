"""int8 and the ONNX export give no torch warnings about what gcdtrav does on purpose; other warnings still show."""

from __future__ import annotations

import warnings
from pathlib import Path

import pytest

pytest.importorskip("torch")

import torch
from gcdtrav.service.backends.clipseg import ClipSegBackend
from gcdtrav.service.backends.expected_warnings import expected_torch_warnings
from gcdtrav.service.backends.machine import available_precisions


@pytest.mark.parametrize("precision", ["int8", "ort-int8"])
def test_int8_and_the_onnx_export_are_quiet(tiny_model_dir: Path, tmp_path: Path, precision: str) -> None:
    if precision not in available_precisions():
        pytest.skip(f"{precision} is not available here")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ClipSegBackend(str(tiny_model_dir), precision=precision, cache_dir=tmp_path)
    noisy = [
        str(w.message)[:80]
        for w in caught
        if issubclass(w.category, torch.jit.TracerWarning) or "quantiz" in str(w.message) or "ONNX" in str(w.message)
    ]
    assert noisy == []


def test_a_warning_that_tells_the_user_something_still_shows() -> None:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with expected_torch_warnings(tracing=True):
            warnings.warn("the checkpoint has no decoder weights", UserWarning, stacklevel=1)
    assert [str(w.message) for w in caught] == ["the checkpoint has no decoder weights"]
