"""`gcdtrav bench`: per-frame cost of every backend mode of your checkpoint on this machine, in one process.

Rows: transformers' naive forward; the fast path in every precision this machine runs; attention and
thread variants; cost against the number of anchors and the input size; one frame in its stages
(preprocessing, vision transformer, decoder and upsampling, engine, encoding) with each one's share, and
this machine's floor for the frame's matrix products; the GCD engine and map encoding alone. Parity of each
fast mode against fp32 is measured on logits brought to a trained model's scale (see ``parity``). The
repository's ``benchmarks/bench.py`` runs the same on random weights of the real architecture and adds the
service rows (zenoh on loopback, simulated robots)."""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import threading
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from gcdtrav.schemas.anchors import Anchor, AnchorSet, default_anchor_set
from gcdtrav.schemas.config import EngineSettings
from gcdtrav.schemas.images import encode_maps_png16
from gcdtrav.service.backends.modes import runtime_mode
from gcdtrav.service.backends.precision_choice import PARITY_P99_DT_LIMIT, parity, synthetic_image
from gcdtrav.service.backends.timing import interleaved_ms
from gcdtrav.service.commands.doctor import machine_info
from gcdtrav.service.engine import gcd
from gcdtrav.service.engine.maps import compute_maps
from numpy.typing import NDArray

# ---- measurement helpers ---------------------------------------------------------------------------


def rss_mb(pid: int | None = None) -> float:
    """Resident memory of this process (``pid`` None) or another one, from /proc; NaN where unavailable."""
    try:
        with open(f"/proc/{'self' if pid is None else pid}/statm") as handle:
            return int(handle.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except OSError:
        if pid is not None:
            return float("nan")
        import resource  # not Linux: this process's peak instead

        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


class RssSampler:
    """Peak resident memory of this process or another one while a block runs, sampled every ``interval`` s."""

    def __init__(self, pid: int | None = None, interval: float = 0.005) -> None:
        self.pid, self.interval = pid, interval

    def __enter__(self) -> RssSampler:
        self.peak = rss_mb(self.pid)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            self.peak = max(self.peak, rss_mb(self.pid))

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()


@dataclass
class Row:
    name: str
    group: str
    runs: int
    median_ms: float
    p95_ms: float
    fps: float
    peak_rss_mb: float
    note: str = ""
    extra: dict[str, Any] = field(default_factory=dict)


def time_call(fn: Callable[[], object], runs: int, warmup: int = 1) -> tuple[list[float], float]:
    with RssSampler() as rss:
        times = interleaved_ms({"call": fn}, runs, warmup)["call"]
    return times, rss.peak


def make_row(name: str, group: str, times: list[float], peak: float, note: str = "", **extra: Any) -> Row:
    median = statistics.median(times)
    p95 = float(np.percentile(times, 95))
    return Row(
        name, group, len(times), round(median, 2), round(p95, 2), round(1000 / median, 2), round(peak, 1), note, extra
    )


# ---- parity ----------------------------------------------------------------------------------------


def activation_cosine(reference: list[Any], candidate: list[Any]) -> float:
    """Smallest, over the extracted layers, of the mean per-token cosine similarity of backbone activations."""
    import torch

    values = []
    for a, b in zip(reference, candidate, strict=True):
        values.append(float(torch.nn.functional.cosine_similarity(a.float(), b.float(), dim=-1).mean()))
    return min(values)


# ---- the benchmark ---------------------------------------------------------------------------------


bench_image = synthetic_image


def anchor_set_of(count: int) -> AnchorSet:
    base = default_anchor_set()
    if count <= len(base):
        chosen = np.linspace(0, len(base) - 1, count).round().astype(int)
        return AnchorSet(name=f"{count}", anchors=[base.anchors[i] for i in chosen])
    return AnchorSet(
        name=f"{count}", anchors=[Anchor(concept=f"terrain type {i}", position=i / (count - 1)) for i in range(count)]
    )


class Bench:
    def __init__(
        self, model_dir: Path, runs: int, naive_runs: int, log: Callable[[str], None], cache_dir: Path | None = None
    ) -> None:
        self.model_dir, self.runs, self.naive_runs, self.log = model_dir, runs, naive_runs, log
        self.cache_dir = cache_dir
        self.rows: list[Row] = []
        self.parity: dict[str, dict[str, float]] = {}
        self.image = bench_image()
        self.anchors = default_anchor_set()

    def add(self, row: Row) -> None:
        self.rows.append(row)
        self.log(
            f"  {row.group:>10} | {row.name:<34} median {row.median_ms:9.1f} ms  p95 {row.p95_ms:9.1f} ms  "
            f"rss {row.peak_rss_mb:7.0f} MB {row.note}"
        )

    def frame(self, backend: Any, prepared: object) -> Callable[[], object]:
        return lambda: backend.logits(self.image, prepared)

    def backend(self, precision: str = "fp32", attention: str | None = None):  # type: ignore[no-untyped-def]
        from gcdtrav.service.backends.clipseg import ClipSegBackend

        # fp32 keeps transformers' whole model: it is also the naive reference
        backend = ClipSegBackend(
            str(self.model_dir), precision=precision, keep_reference=precision == "fp32", cache_dir=self.cache_dir
        )
        if attention is not None:
            backend.model.set_attn_implementation(attention)
        return backend

    def run_modes(self, modes: list[str]) -> None:
        import torch

        reference = self.backend("fp32")
        prepared = reference.prepare(self.anchors.concepts)
        pixels = reference.preprocess(self.image)
        ref_logits = [reference.logits(bench_image(seed=s), prepared) for s in range(3)]
        ref_acts = reference.vision_activations(pixels)

        times, peak = time_call(lambda: reference.naive_logits(self.image, self.anchors.concepts), self.naive_runs)
        self.add(make_row("transformers naive forward (fp32)", "mode", times, peak, "ViT once per concept"))
        times, peak = time_call(lambda: reference.logits(self.image, prepared), self.runs)
        self.add(make_row("fast path fp32", "mode", times, peak, "ViT once, 10 layers, batched decoder"))

        for mode in modes:
            backend = self.backend(mode)
            prep = backend.prepare(self.anchors.concepts)
            times, peak = time_call(self.frame(backend, prep), self.runs)
            cand = [backend.logits(bench_image(seed=s), prep) for s in range(3)]
            report = {
                k: max(parity(r, c, self.anchors)[k] for r, c in zip(ref_logits, cand, strict=True))
                for k in ("max_dT", "p99_dT", "max_dU", "p99_dU", "top_anchor_changed")
            }
            report["activation_cosine_min"] = activation_cosine(ref_acts, backend.vision_activations(pixels))
            report["passes"] = float(report["p99_dT"] <= PARITY_P99_DT_LIMIT)
            self.parity[mode] = report
            self.add(
                make_row(f"fast path {mode}", "mode", times, peak, f"p99|dT| {report['p99_dT']:.4f}", parity=report)
            )

        eager = self.backend("fp32", attention="eager")
        prep = eager.prepare(self.anchors.concepts)
        times, peak = time_call(self.frame(eager, prep), self.runs)
        self.add(make_row("fast path fp32, eager attention", "attention", times, peak, "vs SDPA above"))

        threads = torch.get_num_threads()
        if threads > 1:
            torch.set_num_threads(1)
            try:
                times, peak = time_call(lambda: reference.logits(self.image, prepared), self.runs)
                self.add(make_row("fast path fp32, 1 thread", "threads", times, peak, f"default {threads}"))
            finally:
                torch.set_num_threads(threads)

    def run_stages(self, precision: str) -> None:
        """One frame of ``precision`` in its stages, timed in turns (service/backends/timing.py), each with its
        share of their sum, and the machine's floor for the frame's matrix products beside it (issue 60), whole
        and for the two stages that have products. The decoder's row holds its upsampling: ONNX Runtime runs
        both in one graph."""
        import torch
        from gcdtrav.service.backends.floor import DECODER, VISION, frame_shape, measure_floors

        backend = self.backend(precision)
        prepared = backend.prepare(self.anchors.concepts)
        pixels = backend.preprocess(self.image)
        activations = backend.vision_activations(pixels)
        logits = backend.decode(activations, prepared).numpy()
        maps = compute_maps(logits, self.anchors, EngineSettings())
        stages: dict[str, Callable[[], object]] = {
            "preprocessing": lambda: backend.preprocess(self.image),
            VISION: lambda: backend.vision_activations(pixels),
            DECODER: lambda: backend.decode(activations, prepared),
            "GCD engine (T and U)": lambda: compute_maps(logits, self.anchors, EngineSettings()),
            "encoding T and U (PNG)": lambda: encode_maps_png16(maps.traversability, maps.uncertainty),
        }
        with torch.inference_mode(), RssSampler() as rss:
            times = interleaved_ms(stages, self.runs, warmup=1)
        total = sum(statistics.median(t) for t in times.values())
        for name, stage_times in times.items():
            share = f"{100 * statistics.median(stage_times) / total:.0f} % of the frame's stages"
            self.add(make_row(f"{name} ({precision})", "stage", stage_times, rss.peak, share))
        shape = frame_shape(backend.model, backend.vision_tokens, len(self.anchors.concepts))
        for floor in measure_floors(shape, {runtime_mode(precision).trunk}, torch.get_num_threads()):
            arithmetic, peak = floor.arithmetic, f"{floor.peak / 1e9:,.0f} G/s"
            note = f"{shape.matmul_flops / 1e9:.3g} GFLOP, {shape.concepts} anchors, each at its shape's rate"
            self.add(make_row(f"floor: the frame's products in {arithmetic}", "floor", [floor.ms(shape)], 0.0, note))
            for stage, ms in floor.stage_ms(shape).items():
                took = f"the stage took {statistics.median(times[stage]) / ms:.2f}x this"
                self.add(make_row(f"floor: {stage} in {arithmetic}", "floor part", [ms], 0.0, took))
            note = f"every product at the best rate measured, {peak} ({floor.runtime})"
            at_peak = [floor.peak_ms(shape)]
            self.add(make_row(f"floor at peak: the frame in {arithmetic}", "floor peak", at_peak, 0.0, note))

    def fastest_within_parity(self) -> str:
        """What precision auto picks, from this run's rows: the fastest mode within the parity gate."""
        timed = {r.name[len("fast path ") :]: r.median_ms for r in self.rows if r.name.startswith("fast path ")}
        passing = {mode: ms for mode, ms in timed.items() if mode == "fp32" or self.parity.get(mode, {}).get("passes")}
        return min(passing, key=lambda mode: passing[mode])

    def run_sweeps(self, precision: str) -> None:
        from gcdtrav.service.backends.clipseg import Preprocessing

        backend = self.backend(precision)
        for count in (2, 13, 32, 64):
            anchors = anchor_set_of(count)
            prepared = backend.prepare(anchors.concepts)
            times, peak = time_call(self.frame(backend, prepared), self.runs)
            self.add(make_row(f"{count} anchors ({precision})", "anchors", times, peak))
        if runtime_mode(precision).on_onnxruntime:  # an ONNX export is made for the checkpoint's input size
            precision = "fp32"
            backend = self.backend(precision)
        prepared = backend.prepare(self.anchors.concepts)
        default = backend.preprocess
        for size in (224, 352, 448):
            backend.preprocess = Preprocessing(size=size, mean=default.mean, std=default.std)
            times, peak = time_call(lambda: backend.logits(self.image, prepared), self.runs)
            self.add(make_row(f"input {size}x{size} ({precision})", "input", times, peak))
        backend.preprocess = default

    def run_engine(self) -> None:
        rng = np.random.default_rng(0)
        logits = rng.normal(0, 3, size=(13, 352, 352)).astype(np.float32)
        settings = EngineSettings()
        times, peak = time_call(lambda: compute_maps(logits, self.anchors, settings), self.runs * 2)
        self.add(make_row("GCD T and U, 13x352x352", "engine", times, peak))
        weights = gcd.softmax_weights(logits)
        times, peak = time_call(
            lambda: gcd.mixture_statistics(weights, self.anchors.positions, self.anchors.widths), max(3, self.runs // 2)
        )
        self.add(make_row("all statistics incl. modes", "engine", times, peak))
        maps = compute_maps(logits, self.anchors, settings)
        times, peak = time_call(lambda: encode_maps_png16(maps.traversability, maps.uncertainty), self.runs * 2)
        self.add(make_row("encode T and U as 16-bit PNG", "engine", times, peak, "two threads"))

        def engine_and_encoding() -> list[bytes]:
            result = compute_maps(logits, self.anchors, settings)
            return encode_maps_png16(result.traversability, result.uncertainty)

        times, peak = time_call(engine_and_encoding, self.runs * 2)
        self.add(make_row("GCD T and U + PNG encoding", "engine", times, peak, "the service's per-frame engine work"))
        self.run_grid(weights)
        from gcdtrav.service.engine.gcd import gaussian_fit_baseline

        times, peak = time_call(lambda: gaussian_fit_baseline(weights, self.anchors.positions), 3)
        self.add(make_row("gaussian baseline fit", "engine", times, peak))

    def run_grid(self, weights: NDArray[np.float32]) -> None:
        """What a ground grid adds per frame: projection, fusion into 200 x 200 cells, layers and encoding."""
        from gcdtrav.schemas.settings import GridSettings
        from gcdtrav.service.runtime.grids import GridOutputs
        from gcdtrav.service.runtime.history import FrameRecord

        config = GridSettings.model_validate(
            {
                "source": "bench",
                "intrinsics": {"fx": 500, "fy": 500, "cx": 320, "cy": 240, "width": 640, "height": 480},
                "mount": {"z": 1.2, "pitch": 0.35},
                "size_m": 20.0,
                "resolution_m": 0.1,
                "max_range_m": 10.0,
            }
        )
        outputs = GridOutputs([config], len(self.anchors), "bench")
        clock = iter(range(10**6))

        def frame() -> object:
            record = FrameRecord(
                seq=0,
                stamp=float(next(clock)),
                frame_id="",
                weights=weights[:, :1, :1].astype(np.float16),
                anchors=self.anchors,
                image_size=(640, 480),
            )
            fused = outputs.fuse("bench", record, weights)
            return fused.encode() if fused is not None else None

        times, peak = time_call(frame, self.runs * 2)
        self.add(make_row("ground grid: project, fuse, encode", "grid", times, peak, "20 m at 0.1 m, 352x352 cells in"))


def format_table(rows: list[Row]) -> str:
    group, name = max([9, *(len(r.group) for r in rows)]), max([36, *(len(r.name) for r in rows)])
    header = (
        f"| {'group':<{group}} | {'row':<{name}} | {'median ms':>9} | {'p95 ms':>9} | {'frames/s':>8} "
        f"| {'peak RSS MB':>11} | note"
    )
    lines = [header, "|" + "---|" * 7]
    for r in rows:
        lines.append(
            f"| {r.group:<{group}} | {r.name:<{name}} | {r.median_ms:>9.1f} | {r.p95_ms:>9.1f} | {r.fps:>8.2f} | "
            f"{r.peak_rss_mb:>11.0f} | {r.note}"
        )
    return "\n".join(lines)


def machine_header(info: dict[str, Any]) -> str:
    return (
        f"CPU: {info['cpu']}, {info['usable_cores']} usable cores, features {' '.join(info['cpu_features']) or '-'}"
        f"{' (native bf16)' if info['fast_bf16'] else ' (no native bf16)'}; torch {info['torch']} "
        f"({info['torch_threads']} threads), onnxruntime {info['onnxruntime']}"
    )


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    parser = parser or argparse.ArgumentParser(prog="gcdtrav bench", description=__doc__)
    parser.add_argument(
        "--model",
        default=None,
        help="a checkpoint directory or hub id [$GCDTRAV_MODEL, else CIDAS/clipseg-rd64-refined]",
    )
    parser.add_argument("--runs", type=int, default=7, help="timed runs per row (after one warm-up) [7]")
    parser.add_argument("--naive-runs", type=int, default=5, help="timed runs of the slow naive forward [5]")
    parser.add_argument("--modes", default="", help="fast modes compared with fp32 [every mode this machine can run]")
    parser.add_argument("--skip", default="", help="comma list of parts to skip: modes,sweeps,stages,engine")
    parser.add_argument("--out", type=Path, default=Path("gcdtrav-bench.json"), help="JSON output [gcdtrav-bench.json]")
    return parser


# More rows after the model's: (bench, precision picked, parts to skip) -> None. benchmarks/bench.py adds zenoh's.
MoreRows = Callable[[Bench, str, set[str]], None]


def log_line(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def run(args: argparse.Namespace, cache_dir: Path | None = None, more_rows: MoreRows | None = None) -> int:
    from gcdtrav.service.backends import default_model
    from gcdtrav.service.backends.machine import available_precisions

    skip = {part.strip() for part in args.skip.split(",") if part.strip()}
    bench = Bench(Path(args.model or default_model()), args.runs, args.naive_runs, log_line, cache_dir)
    info = machine_info()
    log_line(machine_header(info))
    modes = [m for m in args.modes.split(",") if m] or [m for m in available_precisions() if m != "fp32"]
    default_precision = "fp32"
    if "modes" not in skip:
        log_line("backend modes (13 anchors, 640x480 image resized to 352x352):")
        bench.run_modes(modes)
        default_precision = bench.fastest_within_parity()
        log_line(f"precision auto would pick {default_precision} (fastest row within the parity gate)")
    if "sweeps" not in skip:
        log_line(f"cost against anchors and input size ({default_precision}):")
        bench.run_sweeps(default_precision)
    if "stages" not in skip:
        log_line(f"one frame in stages ({default_precision}), and this machine's floor for it:")
        bench.run_stages(default_precision)
    if "engine" not in skip:
        log_line("engine and encoding alone:")
        bench.run_engine()
    if more_rows is not None:
        more_rows(bench, default_precision, skip)
    summary = {
        "machine": info,
        "default_precision": default_precision,
        "parity_method": parity.__doc__,
        "parity_limit_p99_dT": PARITY_P99_DT_LIMIT,
        "parity": bench.parity,
        "rows": [asdict(r) for r in bench.rows],
    }
    naive = next((r for r in bench.rows if r.name.startswith("transformers naive")), None)
    fast = next((r for r in bench.rows if r.name == f"fast path {default_precision}"), None)
    if naive and fast:
        summary["speedup_default_vs_naive"] = round(naive.median_ms / fast.median_ms, 1)
    floor = next((r for r in bench.rows if r.group == "floor"), None)
    peak = next((r for r in bench.rows if r.group == "floor peak"), None)
    if fast and floor and peak:
        summary["default_vs_floor"] = round(fast.median_ms / floor.median_ms, 2)
        summary["default_vs_peak_floor"] = round(fast.median_ms / peak.median_ms, 2)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(summary, indent=2) + "\n", "utf-8")
    print(machine_header(info))
    print(format_table(bench.rows))
    if bench.parity:
        print("\nparity against fp32 at a trained model's logit scale (worst of 3 images; see parity()):")
        for mode, report in bench.parity.items():
            print(f"  {mode}: " + ", ".join(f"{k} {v:.4g}" for k, v in report.items()))
    fp32 = next((r for r in bench.rows if r.name == "fast path fp32"), None)
    if fp32 and naive:
        print("\nframes/s against this project's fp32 fast path and transformers' naive forward (same run):")
        for row in bench.rows:
            if row.group == "mode" and row.name.startswith("fast path"):
                print(
                    f"  {row.name[len('fast path ') :]:<14} {fp32.median_ms / row.median_ms:5.2f}x fp32, "
                    f"{naive.median_ms / row.median_ms:6.1f}x naive"
                )
    if floor and "default_vs_floor" in summary:
        print(
            f"\ndefault ({default_precision}): {summary['default_vs_floor']}x this machine's floor ({floor.name}), "
            f"{summary['default_vs_peak_floor']}x the floor at peak"
        )
    if "speedup_default_vs_naive" in summary:
        print(
            f"\ndefault ({default_precision}) vs transformers' naive forward: "
            f"{summary['speedup_default_vs_naive']}x faster"
        )
    print(f"written: {args.out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    return run(build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
