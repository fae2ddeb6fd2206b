"""The store of experience pairs (issue 46, docs/calibration.md "Where pairs live"), on SQLite and PostgreSQL:

- **append**: pairs/s one instance appends (onto the largest store of the run), in the outbox's batches
  (``BATCH_PAIRS``, a loaded writer) and in one outcome's pairs (5 cells: a writer that keeps up), each a
  committed transaction, durable (SQLite synchronous=FULL in WAL, PostgreSQL fsync on);
- **bytes per pair** on disk (SQLite: the file after a checkpoint; PostgreSQL: the table with its index);
- at 10^4 ... 10^7 pairs of the paper's 8 concepts: a **calibration** report as the service answers it
  (``ExperienceStore.report``: the sums the store keeps, the catch-up, AUSE and Spearman over the newest
  10,000 pairs; issue 57), for all pairs, the last hour and by source; the **catch-up** after a swap (a new set
  grading every retained pair once); up to 10^6 also the time to **read** one tuple's pairs, the **direct**
  calibration over them (what a report cost before the sums) and a **fit** (``propose``).

    python -m benchmarks.store                  # 10^4, 10^5, 10^6 pairs
    python -m benchmarks.store --largest 10000000
    python -m benchmarks.store --quick          # 10^3 and 10^4: a smoke check (tests/benchmarks/)
    python -m benchmarks.store --backends sqlite

PostgreSQL is a throw-away cluster on loopback (tests/postgres_cluster.py: Debian's postgresql, fsync on);
medians of ``--repeats`` runs. The machine's CPU and load average are printed with the table.
"""

from __future__ import annotations

import argparse
import json
import os
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import closing, contextmanager
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the throw-away cluster
from gcdtrav.schemas.anchors import AnchorSet, default_anchor_set
from gcdtrav.service.experience.calibration import calibration_figures, pair_sums
from gcdtrav.service.experience.fitter import FitOptions, propose
from gcdtrav.service.experience.graded import grading_key
from gcdtrav.service.experience.store import ExperienceStore, as_pairs
from gcdtrav.service.store import PairRecord, Store, concept_key
from gcdtrav.service.store.outbox import BATCH_PAIRS, PairOutbox
from gcdtrav.service.store.sqlite import SqliteStore

ANCHORS = default_anchor_set()
CONCEPTS = concept_key(ANCHORS.concepts)
TAU = 0.3
GRADED = grading_key(ANCHORS, TAU)
DIRECT_UP_TO = 1_000_000  # reading every pair, the direct calibration and a fit: not beyond this
OUTCOME_CELLS = 5  # one outcome pairs the cells under a 0.6 m footprint at 0.2 m: about 5
FILL_BATCH = 20_000
NO_BOUND = 2**62


def records(count: int, start: int, rng: np.random.Generator) -> list[PairRecord]:
    """Pairs as a drive makes them: weights on the simplex (a few concepts strong), outcomes in [0, 1], graded
    as the experience grades them when it pairs (their calibration sums under the active set)."""
    weights = rng.dirichlet(np.full(len(CONCEPTS), 0.3), count).astype(np.float32)
    outcomes = np.clip(weights @ np.linspace(0.0, 1.0, len(CONCEPTS)) + rng.normal(0, 0.1, count), 0, 1)
    order = [CONCEPTS.index(c) for c in ANCHORS.concepts]
    sums = pair_sums(weights[:, order].astype(np.float64), outcomes, ANCHORS, TAU)
    return [PairRecord(CONCEPTS, weights[k], float(outcomes[k]), 1.7e9 + (start + k) * 0.05, k % 3, ANCHORS.version,
                       f"robot{k % 4}/cam", "bench", sums[k], GRADED) for k in range(count)]  # fmt: skip


def timed(action: Callable[[], object], repeats: int) -> float:
    """The median wall time of ``action``, s."""
    times = []
    for _ in range(repeats):
        began = time.perf_counter()
        action()
        times.append(time.perf_counter() - began)
    return statistics.median(times)


def append_rate(store: Store, batch: int, total: int, rng: np.random.Generator) -> float:
    """Pairs/s appending ``total`` pairs in transactions of ``batch``."""
    chunks = [records(batch, k * batch, rng) for k in range(max(1, total // batch))]
    began = time.perf_counter()
    for chunk in chunks:
        store.append_pairs(chunk, NO_BOUND, NO_BOUND)
    return len(chunks) * batch / (time.perf_counter() - began)


def fill_to(store: Store, count: int, rng: np.random.Generator) -> None:
    have = store.totals().pairs
    while have < count:
        step = min(FILL_BATCH, count - have)
        store.append_pairs(records(step, have, rng), NO_BOUND, NO_BOUND)
        have += step


def calibrate(store: Store) -> None:
    pairs = as_pairs(store.pairs(CONCEPTS))
    calibration_figures(pairs.weights_for(ANCHORS), pairs.outcomes, ANCHORS, TAU)


def reporter(store: Store) -> ExperienceStore:
    """The service's reports over ``store``: an outbox that holds it (nothing is queued, so none is written)."""
    outbox = PairOutbox(lambda: store, store.backend, store.location, 1, NO_BOUND, NO_BOUND)
    outbox.open_now()
    return ExperienceStore(outbox, "robot0/cam", 2.0, "bench", tau=TAU)


def swapped(count: int) -> AnchorSet:
    """A set of the same concepts that has graded nothing yet (its first anchor moved a little)."""
    anchors = [a.model_copy(update={"position": a.position + 1e-6 * len(str(count))}) if k == 0 else a
               for k, a in enumerate(ANCHORS.anchors)]  # fmt: skip
    return AnchorSet(anchors=anchors)


def fit(store: Store) -> None:
    propose(as_pairs(store.pairs(CONCEPTS)), ANCHORS, FitOptions())


def measure(store: Store, size_of: Callable[[], int], sizes: list[int], repeats: int) -> dict[str, Any]:
    """The sizes first (a fresh store filled up), then the appends, onto the largest store."""
    rng = np.random.default_rng(0)
    result: dict[str, Any] = {"sizes": {}}
    for count in sizes:
        fill_to(store, count, rng)
        pairs, reports = store.totals().pairs, reporter(store)
        began = time.perf_counter()
        reports.report(swapped(count), TAU)  # the first report of a new set: it grades every retained pair once
        row: dict[str, Any] = {"pairs": pairs, "bytes_per_pair": size_of() / pairs,
                               "catch_up_s": time.perf_counter() - began}  # fmt: skip
        for name, options in (("all", {}), ("hour", {"window": "hour"}), ("by_source", {"by_source": True})):
            row[f"report_{name}_s"] = timed(partial(reports.report, ANCHORS, TAU, **options), repeats)
        if count <= DIRECT_UP_TO:
            row["read_s"] = timed(lambda: store.pairs(CONCEPTS), repeats)
            row["direct_calibration_s"] = timed(lambda: calibrate(store), repeats)
            row["fit_s"] = timed(lambda: fit(store), max(1, repeats // 2))
        result["sizes"][str(count)] = row
        print(f"  {store.backend} {count}: {result['sizes'][str(count)]}", flush=True)
    result["append_pairs_per_s"] = {
        f"batch {BATCH_PAIRS}": append_rate(store, BATCH_PAIRS, 10 * BATCH_PAIRS, rng),
        f"batch {OUTCOME_CELLS}": append_rate(store, OUTCOME_CELLS, 200 * OUTCOME_CELLS, rng),
    }
    return result


@contextmanager
def sqlite_store() -> Iterator[tuple[Store, Callable[[], int]]]:
    with tempfile.TemporaryDirectory(prefix="gcdtrav-bench-store-") as folder:
        path = Path(folder) / "bench.store.sqlite3"
        store = SqliteStore(path)

        def size() -> int:
            with closing(sqlite3.connect(path)) as connection:  # the WAL folded into the file first
                connection.execute("PRAGMA wal_checkpoint(TRUNCATE)")
            return sum(p.stat().st_size for p in Path(folder).iterdir())

        try:
            yield store, size
        finally:
            store.close()


@contextmanager
def postgresql_store() -> Iterator[tuple[Store, Callable[[], int]]]:
    from gcdtrav.service.store.postgres import PostgresStore
    from postgres_cluster import postgres_cluster

    with postgres_cluster(durable=True) as cluster:
        store = PostgresStore(cluster.create_database("bench"), cluster.password)

        def size() -> int:
            with store._transaction(None) as cursor:
                cursor.execute("SELECT pg_total_relation_size('pairs')")
                return int(cursor.fetchone()[0])

        try:
            yield store, size
        finally:
            store.close()


BACKENDS = {"sqlite": sqlite_store, "postgresql": postgresql_store}


def machine() -> dict[str, Any]:
    cpu = subprocess.run(["lscpu"], capture_output=True, text=True, check=False).stdout
    model = next((line.split(":", 1)[1].strip() for line in cpu.splitlines() if line.startswith("Model name")), "?")
    return {"cpu": model, "cores": os.cpu_count(), "load_average": [round(x, 2) for x in os.getloadavg()]}


def run(sizes: list[int], backends: list[str], repeats: int) -> dict[str, Any]:
    result: dict[str, Any] = {"machine": machine(), "sizes": sizes, "backends": {}}
    for name in backends:
        with BACKENDS[name]() as (store, size):
            result["backends"][name] = measure(store, size, sizes, repeats)
    result["machine"]["load_average_after"] = [round(x, 2) for x in os.getloadavg()]
    return result


def table(result: dict[str, Any]) -> str:
    m = result["machine"]
    lines = [
        f"{m['cpu']}, {m['cores']} cores; load average {m['load_average']} before, {m['load_average_after']} after",
        "",
        "| backend | append, pairs/s (batch 2000 / batch 5) | pairs | bytes/pair | report: all / last hour / by "
        "source, ms | catch-up after a swap, s | read, s | direct calibration, s | fit, s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, row in result["backends"].items():
        rates = " / ".join(f"{rate:,.0f}" for rate in row["append_pairs_per_s"].values())
        for count, size in row["sizes"].items():
            reports = " / ".join(f"{1000 * size[f'report_{w}_s']:.0f}" for w in ("all", "hour", "by_source"))
            direct = [f"{size[k]:.2f}" if k in size else "-" for k in ("read_s", "direct_calibration_s", "fit_s")]
            lines.append(
                f"| {name} | {rates} | {int(count):,} | {size['bytes_per_pair']:.0f} | {reports} | "
                f"{size['catch_up_s']:.1f} | {' | '.join(direct)} |"
            )
            rates = '"'
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="10^3 and 10^4 pairs, one repeat: a smoke check")
    parser.add_argument("--backends", nargs="+", choices=sorted(BACKENDS), default=["sqlite", "postgresql"])
    parser.add_argument("--repeats", type=int, default=3, help="runs per timing; the median is shown [3]")
    parser.add_argument("--largest", type=int, default=1_000_000, help="the largest store measured [10^6]")
    parser.add_argument("--out", type=Path, help="also write the result as JSON")
    args = parser.parse_args(argv)
    sizes = (
        [1_000, 10_000] if args.quick else [n for n in (10_000, 100_000, 1_000_000, 10_000_000) if n <= args.largest]
    )
    result = run(sizes, args.backends, 1 if args.quick else args.repeats)
    print(table(result))
    if args.out:
        args.out.write_text(json.dumps(result, indent=2) + "\n", "utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
