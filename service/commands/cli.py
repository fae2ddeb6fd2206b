"""The `gcdtrav` command: `infer` (offline), `serve` (Zenoh service), `bench` (benchmarks), `doctor` (this
machine's modes: the first thing to run on a new box), and the torch-free operator commands `status` and
`anchors` (gcdtrav.client.commands.operator), `view` (Foxglove, gcdtrav.client.view), `relay` (on the robot,
gcdtrav.client.commands.relay) and `identity` (certificates and access control, gcdtrav.client.commands.identity)."""

from __future__ import annotations

import argparse
import importlib.util
import json
import logging
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from gcdtrav.client.commands import identity as identity_command
from gcdtrav.client.commands import operator
from gcdtrav.client.commands import relay as relay_command
from gcdtrav.client.commands import view as view_command
from gcdtrav.client.commands.experience import proposal_lines, refusal
from gcdtrav.schemas.anchors import AnchorSet, AnchorSetError, default_anchor_set
from gcdtrav.schemas.config import EngineSettings, Method
from gcdtrav.schemas.settings import PRECISIONS, SettingsError
from gcdtrav.service.backends import default_model

if TYPE_CHECKING:
    from gcdtrav.service.experience.dataset_fit import FitRun

SERVICE_MODULES = ("torch", "transformers", "matplotlib", "tqdm", "prometheus_client")
EXIT_FAILURES = 1  # some inputs could not be processed
EXIT_USAGE = 2  # bad configuration: anchor file, model weights, arguments
CACHE_DIR_HELP = (
    "ONNX exports and the measurement of precision auto, shared by doctor, infer, eval and serve "
    "[$XDG_CACHE_HOME/gcdtrav, else ~/.cache/gcdtrav]"
)
# Peer mode listens on a port zenoh picks unless told otherwise: serve listens on zenoh's usual port, so that
# another machine can connect with -e tcp/HOST:7447 (a taken port falls back to zenoh's pick, with a warning).
DEFAULT_SERVE_LISTEN = "tcp/0.0.0.0:7447"
PRECISION_HELP = (
    "model arithmetic: auto = the fastest mode within the parity gate, measured on this machine at the first "
    "start and cached (gcdtrav doctor shows the figures)"
)


def parse_probe(text: str) -> tuple[int, int]:
    try:
        x, y = (int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"probe '{text}' must be X,Y in image pixels, e.g. 120,340") from None
    return x, y


def load_anchors(path: str | None) -> AnchorSet:
    return default_anchor_set() if path is None else AnchorSet.load(path)


def add_model_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--model",
        help="CLIPSeg checkpoint: a local directory (Hugging Face layout) or a hub id "
        "[env GCDTRAV_MODEL, default CIDAS/clipseg-rd64-refined]",
    )
    parser.add_argument("--anchors", help="anchor-set file (JSON or YAML) [default: the paper's set]")
    parser.add_argument(
        "--method",
        choices=[m.value for m in Method],
        default=Method.GCD.value,
        help="gcd (the paper), argmax or gaussian (its baselines) [default: gcd]",
    )
    parser.add_argument("--temperature", type=float, default=1.0, help="softmax temperature [default: 1]")
    parser.add_argument(
        "--normalize-u",
        action="store_true",
        help="divide U by the largest sigma the anchor set can produce, so U spans [0, 1]",
    )
    parser.add_argument("--precision", choices=PRECISIONS, default="auto", help=PRECISION_HELP + " [auto]")
    parser.add_argument("--cache-dir", type=Path, help=CACHE_DIR_HELP)


DESCRIPTION = (
    "Traversability T and uncertainty U of every image patch. Start with `gcdtrav doctor --model DIR` on a new "
    "box, then `gcdtrav serve`; `infer` works on image files offline. status, anchors, probe, calibration, answer, "
    "view and relay need no torch (the operator's laptop, the robot). `gcdtrav COMMAND --help` for each."
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="gcdtrav", description=DESCRIPTION)
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    commands = parser.add_subparsers(dest="command", required=True)

    infer = commands.add_parser("infer", help="images on disk -> T/U maps, overlays, figures")
    infer.add_argument("images", nargs="+", type=Path, help="image files (JPEG, PNG, ...)")
    infer.add_argument("--out", type=Path, required=True, help="output directory (one folder per image)")
    add_model_arguments(infer)
    infer.add_argument(
        "--probe",
        type=parse_probe,
        action="append",
        default=[],
        metavar="X,Y",
        help="pixel whose context distribution is printed, and drawn with --figure (repeatable); outside an "
        "image it is an error (exit 2) [figure default: the most certain, median and most ambiguous pixels]",
    )
    infer.add_argument(
        "--save-raw",
        action="store_true",
        help="also write logits.npy, T.npy, U.npy (backend resolution) and anchors.json",
    )
    infer.add_argument(
        "--figure",
        action=argparse.BooleanOptionalAction,
        default=False,
        help="also draw figure.png (maps and the probes' context distributions, like the paper's Fig. 2); "
        "about 0.8 s per image, more than the inference itself [off]",
    )

    serve = commands.add_parser(
        "serve",
        help="the Zenoh service: images in, T/U maps out, queries",
        description="Run the traversability service on the Zenoh bus. Settings: "
        "defaults < --settings YAML < GCDTRAV_* environment < flags.",
    )
    from gcdtrav.client.session.zenoh_args import add_zenoh_arguments

    add_zenoh_arguments(serve)
    group = serve.add_argument_group("service")
    group.add_argument("--settings", metavar="FILE", help="service settings (YAML)")
    group.add_argument("--prefix", help="key prefix of the service's keys [default: gcdtrav]")
    group.add_argument(
        "--input",
        dest="inputs",
        action="append",
        metavar="KEYEXPR",
        help="image key expression to subscribe to (repeatable) [default: gcdtrav/in/**]",
    )
    group.add_argument("--model", help="CLIPSeg directory or hub id [env GCDTRAV_MODEL]")
    group.add_argument(
        "--anchors",
        dest="anchors_file",
        help="anchor set to start with; a set accepted at runtime (state file) takes precedence",
    )
    group.add_argument("--method", choices=[m.value for m in Method])
    group.add_argument("--history", type=int, help="frames per source kept for queries [8]")
    group.add_argument(
        "--state-dir",
        help="where the accepted anchor set is kept [$XDG_STATE_HOME/gcdtrav, else ~/.local/state/gcdtrav]",
    )
    group.add_argument("--cache-dir", help=CACHE_DIR_HELP)
    group.add_argument("--instance", help="instance name [default: host-pid]")
    group.add_argument(
        "--full-resolution", action="store_true", default=None, help="also publish T and U at the input image's size"
    )
    group.add_argument(
        "--no-preview",
        dest="preview",
        action="store_false",
        default=None,
        help="don't publish the colourised JPEG preview",
    )
    group.add_argument("--max-payload-bytes", type=int, help="larger inputs are rejected [20 MB]")
    group.add_argument("--threads", type=int, help="torch threads [the usable CPUs, within a container's CPU quota]")
    group.add_argument("--precision", choices=PRECISIONS, help=PRECISION_HELP + " [auto]")
    group.add_argument(
        "--metrics-port",
        type=int,
        metavar="PORT",
        help="serve Prometheus metrics on http://ADDRESS:PORT/metrics (docs/metrics.md); 0: off [0]",
    )
    group.add_argument("--metrics-address", metavar="ADDRESS", help="address of the metrics port [0.0.0.0]")
    group.add_argument(
        "--measure-first",
        dest="measure_before_serving",
        action="store_true",
        default=None,
        help="precision auto with nothing cached: measure the modes before serving "
        "[off: serve fp32 at once, measure in the background, then switch]",
    )

    evaluate = commands.add_parser(
        "eval",
        help="compare T and U with label-derived ground truth",
        description="The paper's evaluation on GOOSE-format (or RUGD, or generic) data.",
    )
    evaluate.add_argument("--dataset", choices=["goose", "rugd", "generic"], required=True)
    evaluate.add_argument("--root", type=Path, required=True, help="the dataset's root folder")
    evaluate.add_argument("--split", help="goose: val|train|test [val]; rugd: comma list of sequences")
    evaluate.add_argument("--methods", default="gcd,argmax,gaussian", help="comma list [gcd,argmax,gaussian]")
    evaluate.add_argument(
        "--mapping", help="label -> traversability YAML [the shipped one for goose and rugd; required for generic]"
    )
    evaluate.add_argument("--model", help="CLIPSeg directory or hub id [env GCDTRAV_MODEL]")
    evaluate.add_argument("--anchors", help="anchor-set file [the paper's set]")
    evaluate.add_argument("--precision", choices=PRECISIONS, default="auto", help=PRECISION_HELP + " [auto]")
    evaluate.add_argument("--cache-dir", type=Path, help=CACHE_DIR_HELP)
    evaluate.add_argument("--temperature", type=float, default=1.0)
    evaluate.add_argument("--grid", type=int, default=8, help="sample every GRID-th pixel in x and y [8]")
    evaluate.add_argument("--out", type=Path, default=Path("eval_out"), help="output folder [eval_out]")
    evaluate.add_argument("--limit", type=int, help="only the first N images")
    evaluate.add_argument("--no-figures", action="store_true")
    evaluate.add_argument(
        "--fit-anchors",
        action="store_true",
        help="fit anchor positions and widths to the labels (earlier images), grade them on the later ones, "
        "write OUT/proposed-anchors.yaml (docs/calibration.md)",
    )

    from gcdtrav.service.commands import bench

    bench.build_parser(
        commands.add_parser("bench", help="benchmark every backend mode on this machine", description=bench.__doc__)
    )
    from gcdtrav.service.commands import doctor

    doctor.build_parser(
        commands.add_parser(
            "doctor",
            help="this machine: CPU features, versions, weights, every precision mode's time and parity",
            description=doctor.__doc__,
        )
    )
    operator.add_operator_commands(commands)
    view_command.add_view_command(commands)
    relay_command.add_relay_command(commands)
    identity_command.add_identity_command(commands)
    return parser


def build_pipeline(args: argparse.Namespace):  # type: ignore[no-untyped-def]
    """Anchors first (cheap to validate), then the model (slow to load)."""
    from gcdtrav.service.backends.cpus import set_torch_threads
    from gcdtrav.service.pipeline import clipseg_pipeline

    anchors = load_anchors(args.anchors)
    settings = EngineSettings(
        method=Method(args.method), temperature=args.temperature, normalize_uncertainty=args.normalize_u
    )
    set_torch_threads(None)  # as serve and doctor do: auto's cached measurement is keyed by the threads
    return clipseg_pipeline(args.model, args.precision, anchors, settings, args.cache_dir)


def cmd_infer(args: argparse.Namespace) -> int:
    from gcdtrav.service.commands.infer import InferOptions, ProbeOutsideImage, run_infer

    pipeline = build_pipeline(args)
    options = InferOptions(out_dir=args.out, probes=args.probe, save_raw=args.save_raw, figure=args.figure)
    try:
        failures = run_infer(pipeline, args.images, options)
    except ProbeOutsideImage as err:
        print(f"gcdtrav infer: {err}", file=sys.stderr)
        return EXIT_USAGE
    done = len(args.images) - failures
    print(f"{done} of {len(args.images)} images written to {args.out}", file=sys.stderr)
    return EXIT_FAILURES if failures else 0


def serve_settings(args: argparse.Namespace):  # type: ignore[no-untyped-def]
    from gcdtrav.schemas.settings import load_settings

    overrides = {
        name: getattr(args, name)
        for name in (
            "prefix",
            "inputs",
            "model",
            "anchors_file",
            "history",
            "state_dir",
            "cache_dir",
            "instance",
            "full_resolution",
            "preview",
            "max_payload_bytes",
            "threads",
            "precision",
            "measure_before_serving",
            "metrics_port",
            "metrics_address",
        )
    }
    if args.method is not None:
        overrides["engine"] = {"method": args.method}
    return load_settings(args.settings, overrides)


def cmd_serve(args: argparse.Namespace) -> int:
    from gcdtrav.client.session.zenoh_args import zenoh_config_from_args
    from gcdtrav.service.commands.serve import run_service

    settings = serve_settings(args)
    try:
        config = zenoh_config_from_args(args)
    except Exception as err:  # zenoh raises its own error type for bad config files and values
        print(f"gcdtrav: invalid zenoh configuration: {err}", file=sys.stderr)
        return EXIT_USAGE
    if args.mode is None:
        config.insert_json5("mode", '"peer"')
    fallback = None
    if args.mode in (None, "peer") and not listens_by_choice(args):
        fallback = zenoh_config_from_args(args)  # zenoh's own pick of a port, if 7447 is taken
        fallback.insert_json5("mode", '"peer"')
        config.insert_json5("listen/endpoints", json.dumps([DEFAULT_SERVE_LISTEN]))
    return run_service(settings, config, fallback)


def listens_by_choice(args: argparse.Namespace) -> bool:
    """The user said where to listen: -l, a config file, or --cfg listen/..."""
    return bool(args.listen or args.config or any(item.startswith("listen") for item in args.cfg))


def cmd_eval(args: argparse.Namespace) -> int:
    from gcdtrav.service.backends.clipseg import ClipSegBackend
    from gcdtrav.service.eval.datasets import DatasetError, load_dataset
    from gcdtrav.service.eval.mapping import load_mapping
    from gcdtrav.service.eval.run import EvalOptions, run_eval

    try:
        methods = [Method(m.strip()) for m in args.methods.split(",") if m.strip()]
    except ValueError:
        print(f"gcdtrav: --methods must list gcd, argmax, gaussian; got '{args.methods}'", file=sys.stderr)
        return EXIT_USAGE
    anchors = load_anchors(args.anchors)
    try:
        dataset = load_dataset(args.dataset, args.root, args.split)
        if args.mapping is None and args.dataset == "generic":
            raise DatasetError("a generic dataset needs --mapping FILE.yaml (class name: value or ignore)")
        table = load_mapping(args.mapping or args.dataset, dataset.class_names)
    except DatasetError as err:
        print(f"gcdtrav: {err}", file=sys.stderr)
        return EXIT_USAGE
    from gcdtrav.service.backends.cpus import set_torch_threads

    set_torch_threads(None)
    backend = ClipSegBackend(args.model or default_model(), precision=args.precision, cache_dir=args.cache_dir)
    options = EvalOptions(
        out_dir=args.out,
        methods=methods,
        grid=args.grid,
        limit=args.limit,
        temperature=args.temperature,
        figures=not args.no_figures,
    )
    if args.fit_anchors:
        from gcdtrav.service.experience.dataset_fit import fit_on_dataset
        from gcdtrav.service.experience.fitter import FitOptions

        try:
            fit = fit_on_dataset(backend, anchors, dataset, table, args.out, FitOptions(), args.grid,
                                 args.temperature, args.limit)  # fmt: skip
        except (DatasetError, ValueError) as err:
            print(f"gcdtrav: {err}", file=sys.stderr)
            return EXIT_FAILURES
        print_fit(fit)
        return EXIT_FAILURES if fit.failures else 0
    try:
        report = run_eval(backend, anchors, dataset, table, options)
    except DatasetError as err:
        print(f"gcdtrav: {err}", file=sys.stderr)
        return EXIT_FAILURES
    for failure in report["failures"]:
        print(f"error: {failure}", file=sys.stderr)
    print(report["summary_table"])
    print(f"{report['images']} images evaluated; results in {args.out}", file=sys.stderr)
    return EXIT_FAILURES if report["failures"] else 0


def print_fit(fit: FitRun) -> None:
    """`gcdtrav eval --fit-anchors`: the proposal as `gcdtrav anchors propose` prints it, then where it is."""
    for failure in fit.failures:
        print(f"error: {failure}", file=sys.stderr)
    print("\n".join(proposal_lines(fit.proposal)))
    refused = refusal(fit.proposal.judged())
    advice = f"not recommended: {refused}" if refused else "judged better"
    print(f"\nproposed set: {fit.proposed_file} ({advice}); gcdtrav anchors set {fit.proposed_file} --dry-run")


def cmd_bench(args: argparse.Namespace) -> int:
    from gcdtrav.service.commands import bench

    return bench.run(args)


def cmd_doctor(args: argparse.Namespace) -> int:
    from gcdtrav.service.commands import doctor

    return doctor.run(args)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    if args.command in operator.COMMANDS:  # torch-free: they work from the base install
        return operator.run(args)
    if args.command == "view":  # torch-free too, with the view extra
        return view_command.run(args)
    if args.command == "relay":  # torch-free: the robot's side of a slow link
        return relay_command.run(args)
    if args.command == "identity":  # torch-free: certificates and the routers' access control
        return identity_command.run(args)
    handlers = {"infer": cmd_infer, "serve": cmd_serve, "bench": cmd_bench, "eval": cmd_eval, "doctor": cmd_doctor}
    from gcdtrav.service.backends.base import ModelUnavailableError

    missing = [name for name in SERVICE_MODULES if importlib.util.find_spec(name) is None]
    if missing:  # the client-only install: say what to install instead of a traceback
        print(
            f"gcdtrav {args.command}: needs {', '.join(missing)}; install CPU torch, then the service extra: "
            "pip install torch==2.13.0 && pip install 'gcdtrav[service]'",
            file=sys.stderr,
        )
        return EXIT_USAGE
    try:
        return handlers[args.command](args)
    except (AnchorSetError, SettingsError) as err:
        print(f"gcdtrav: {err}", file=sys.stderr)
        return EXIT_USAGE
    except ModelUnavailableError as err:
        print(f"gcdtrav: {err}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
