"""benchmarks/store.py --quick: every figure of the table is measured on SQLite (and PostgreSQL where it is
installed), over the sizes asked for (benchmarks/README.md, "Store")."""

from __future__ import annotations

import pytest
from real_components import postgresql_bin

from benchmarks.store import run, table


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_quick_measures_appends_bytes_and_the_read_calibration_and_fit_times(backend: str) -> None:
    if backend == "postgresql":
        postgresql_bin()  # skipped here without PostgreSQL, a failure in CI
    result = run([1_000, 3_000], [backend], repeats=1)
    row = result["backends"][backend]
    assert [size["pairs"] for size in row["sizes"].values()] == [1_000, 3_000]
    assert all(rate > 0 for rate in row["append_pairs_per_s"].values())
    for size in row["sizes"].values():
        assert 4 * 8 < size["bytes_per_pair"] < 2_000  # the 8 weights at least; never a rewrite's worth
        assert size["read_s"] > 0 and size["direct_calibration_s"] > 0 and size["fit_s"] > 0
        assert size["report_all_s"] > 0 and size["report_hour_s"] > 0 and size["report_by_source_s"] > 0
        assert size["catch_up_s"] > 0
    assert f"| {backend} |" in table(result) and "load average" in table(result)
