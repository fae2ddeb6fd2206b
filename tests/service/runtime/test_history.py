"""FrameHistory at every depth, with one source and several, with and without a byte budget."""

from __future__ import annotations

import numpy as np
import pytest
from gcdtrav.schemas.anchors import default_anchor_set
from gcdtrav.service.runtime.errors import QueryError
from gcdtrav.service.runtime.history import FrameHistory, as_float16

ANCHORS = default_anchor_set()
FRAME_BYTES = len(ANCHORS) * 2 * 3 * 2  # n x 2 x 3 float16


def record(history: FrameHistory, source: str, stamp: float) -> int:
    weights = np.full((len(ANCHORS), 2, 3), 1 / len(ANCHORS), np.float32)
    return history.record(source, weights, ANCHORS, stamp, "cam", (6, 4)).seq


@pytest.mark.parametrize("depth", [1, 2, 8])
@pytest.mark.parametrize("sources", [1, 3])
def test_every_frame_is_queryable_and_counted_at_any_depth(depth: int, sources: int) -> None:
    history = FrameHistory(depth)
    names = [f"r{k}/front" for k in range(sources)]
    for frame in range(2 * depth + 3):
        for name in names:
            seq = record(history, name, stamp=float(frame))
            assert seq == frame
            assert history.get(name, None).seq == frame  # the newest is always kept
            assert history.get(name, seq).stamp == frame
    for name in names:
        kept = [history.get(name, seq).seq for seq in range(depth + 3, 2 * depth + 3)]
        assert kept == list(range(depth + 3, 2 * depth + 3))  # exactly the last `depth`
        with pytest.raises(QueryError, match="is not kept"):
            history.get(name, depth + 2)
    assert history.nbytes == sources * depth * FRAME_BYTES


@pytest.mark.parametrize("depth", [1, 2, 8])
def test_the_budget_evicts_the_oldest_frame_of_any_source(depth: int) -> None:
    history = FrameHistory(depth, budget_bytes=2 * FRAME_BYTES)
    for frame in range(6):
        for name in ("a", "b", "c"):
            record(history, name, float(frame))
            assert history.nbytes <= 2 * FRAME_BYTES
    assert history.get("c", None).seq == 5
    assert history.nbytes == 2 * FRAME_BYTES


@pytest.mark.parametrize("depth", [1, 3])
def test_forgetting_a_source_frees_its_bytes_and_numbering(depth: int) -> None:
    history = FrameHistory(depth)
    for frame in range(4):
        record(history, "a", float(frame))
        record(history, "b", float(frame))
    history.forget("a")
    assert history.nbytes == depth * FRAME_BYTES
    with pytest.raises(QueryError, match="unknown source 'a'"):
        history.get("a", None)
    assert record(history, "a", 9.0) == 0


EDGES = [0.0, -0.0, 1e-8, 6e-8, 1e-5, 0.1, 1 / 3, 1.0, 65504.0, 65519.0, 65520.0, 1e6, -1e6, np.inf, -np.inf, np.nan]


@pytest.mark.parametrize(
    "values",
    [
        np.array(EDGES, np.float32),  # rounding, subnormals, overflow to inf, signed zero, NaN
        np.random.default_rng(3).random((13, 35, 37), dtype=np.float32),
        np.random.default_rng(4).standard_normal((5, 6, 7))[:, ::2, 1:],  # float64, not contiguous
        np.float32(0.25),  # 0-d
        np.zeros((0, 4), np.float32),  # empty
        np.array([1 + 2**-11 + 2**-40, 2**-11 + 2**-30], np.float64),  # float64 halfway cases: rounded once
    ],
    ids=["edges", "weights", "float64-strided", "scalar", "empty", "float64-halfway"],
)
def test_as_float16_is_numpys_cast_bit_for_bit(values: np.ndarray) -> None:
    with np.errstate(over="ignore"):
        expected = np.asarray(values).astype(np.float16)
        got = as_float16(values)
    assert got.dtype == np.float16 and got.shape == expected.shape
    assert np.array_equal(got.view(np.uint16), expected.view(np.uint16))


def test_a_recorded_frame_keeps_its_weights_and_match_as_float16() -> None:
    weights = np.random.default_rng(5).dirichlet(np.ones(len(ANCHORS)), size=(3, 4)).transpose(2, 0, 1)
    match = np.random.default_rng(6).random((3, 4))
    kept = FrameHistory(2).record("r1", weights.astype(np.float32), ANCHORS, 1.0, "cam", (4, 3), match)
    assert kept.weights.dtype == np.float16 and kept.match is not None and kept.match.dtype == np.float16
    assert np.array_equal(kept.weights, weights.astype(np.float32).astype(np.float16))
    assert np.array_equal(kept.match, match.astype(np.float16))
