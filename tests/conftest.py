"""Shared fixtures: a tiny random-weight CLIPSeg saved in the Hugging Face layout, built offline."""

from __future__ import annotations

import os
import sys
import tempfile
import textwrap
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from gcdtrav.schemas.anchors import AnchorSet

pytest_plugins = ["store_fixtures"]  # the store's fixtures over SQLite and PostgreSQL (tests/service/store/)

# Nothing in the test suite may reach a model hub.
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
# ONNX exports and precision measurements go to a cache of this run, never the user's ~/.cache.
os.environ["XDG_CACHE_HOME"] = tempfile.mkdtemp(prefix="gcdtrav-test-cache-")

TINY_INPUT_SIZE = 96  # != the vision config's 64, so position-embedding interpolation is exercised


def build_tiny_clipseg(directory: Path, seed: int = 0) -> Path:
    from tools.random_clipseg import save_random_clipseg

    return save_random_clipseg(directory, preset="tiny", input_size=TINY_INPUT_SIZE, seed=seed)


@pytest.fixture(scope="session")
def tiny_model_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    pytest.importorskip("torch")
    return build_tiny_clipseg(tmp_path_factory.mktemp("tiny-clipseg"))


@pytest.fixture(scope="session")
def tiny_backend(tiny_model_dir: Path):  # type: ignore[no-untyped-def]
    from gcdtrav.service.backends.clipseg import ClipSegBackend

    return ClipSegBackend(str(tiny_model_dir), keep_reference=True)  # naive_logits is the tests' reference


@pytest.fixture()
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


def textured_image(height: int, width: int, seed: int = 0) -> np.ndarray:
    """A deterministic RGB image with structure (so logits vary across patches)."""
    generator = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width]
    base = np.stack([x * 255 // max(width - 1, 1), y * 255 // max(height - 1, 1), (x + y) % 256], axis=2)
    noise = generator.integers(0, 40, size=(height, width, 3))
    return np.clip(base + noise, 0, 255).astype(np.uint8)


def camera_grid(**overrides: Any) -> dict[str, Any]:
    """Grid settings of source 'cam': an 80x60 camera 1 m up, pitched down, 8 m of 0.25 m cells, with a pose."""
    grid = {
        "source": "cam",
        "intrinsics": {"fx": 60, "fy": 60, "cx": 40, "cy": 30, "width": 80, "height": 60},
        "mount": {"z": 1.0, "pitch": 0.6},
        "size_m": 8.0,
        "resolution_m": 0.25,
        "pose_key": "robot/pose",
    }
    return grid | overrides


def torch_free_gcdtrav(*args: str) -> list[str]:
    """The command line of `gcdtrav ARGS` in a fresh interpreter where torch and transformers cannot be imported."""
    code = textwrap.dedent(
        f"""
        import sys
        sys.modules["torch"] = None
        sys.modules["transformers"] = None
        from gcdtrav.service.commands.cli import main
        sys.exit(main({list(args)!r}))
        """
    )
    return [sys.executable, "-c", code]


def three_anchor_set(name: str) -> AnchorSet:
    """A set of its own per ``name`` (water, "terrain NAME", road): distinct versions for swap tests."""
    return AnchorSet.parse(
        {
            "name": name,
            "anchors": [
                {"concept": "water", "position": 0.0},
                {"concept": f"terrain {name}", "position": 0.5},
                {"concept": "road", "position": 1.0},
            ],
        }
    )
