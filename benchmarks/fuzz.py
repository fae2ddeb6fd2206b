"""Fuzz campaign beyond CI: every decoder and parser the service exposes, coverage-guided, at scale.

    pip install atheris
    python -m benchmarks.fuzz                          # 100,000 inputs per target
    python -m benchmarks.fuzz --engine hypothesis --runs 300 --out /tmp/fuzz.json   # the suite's smoke run
    python -m benchmarks.fuzz --runs 2000 --targets anchor_documents selectors

Each target runs in its own process, for ``--runs`` inputs or ``--max-seconds``, whichever comes first, and
stops by itself: under atheris (libFuzzer, coverage-guided, seeded with valid inputs of its kind) where it is
installed, else under hypothesis (random bytes and random edits of the same seeds, not coverage-guided);
``--engine`` picks one. An input is *rejected* when the decoder raises its own error type (the reason is
counted), a *crash* when it raises anything else or when what it accepted breaks a bound (a frame id over
its limit, a pose or intrinsics that are not finite), a *hang* when one call takes over 1 s. Reports per
target: inputs tried, distinct rejection reasons, crashes, hangs, peak RSS of the target's process; writes
the same as JSON (crashing inputs are kept beside it). Everything runs on this machine; nothing is sent
anywhere. The test suite runs a few hundred inputs per target under hypothesis (tests/test_fuzz_campaign.py).
"""

from __future__ import annotations

import argparse
import json
import math
import re
import resource
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

HANG_S = 1.0
FLUSH_EVERY = 500

# ---- the targets: seeds and one call each ------------------------------------------------------------


def _image_seeds() -> list[bytes]:
    import numpy as np
    from gcdtrav.schemas.images import encode_jpeg, encode_png
    from gcdtrav.schemas.messages import ImageEnvelope, PixelEncoding

    small = np.random.default_rng(0).integers(0, 255, size=(12, 16, 3), dtype=np.uint8)
    raw = ImageEnvelope(stamp=1.0, encoding=PixelEncoding.RGB8, width=16, height=12, data=small.tobytes())
    jpeg = ImageEnvelope(stamp=1.0, frame_id="cam", encoding=PixelEncoding.JPEG, width=16, height=12,
                         data=encode_jpeg(small))  # fmt: skip
    return [encode_png(small), encode_jpeg(small), raw.pack(), jpeg.pack()]


def _decode_image(data: bytes) -> None:
    from gcdtrav.schemas.inputs import decode_payload
    from gcdtrav.schemas.limits import MAX_FRAME_ID_CHARS

    # The first byte picks how the payload is labelled, as a peer's encoding would.
    encoding = ["", "image/jpeg", "image/png", "application/msgpack"][data[0] % 4] if data else ""
    frame = decode_payload(data[1:], encoding, 0.0, 2_000_000, 4_000_000)
    _holds(len(frame.frame_id) <= MAX_FRAME_ID_CHARS, "frame_id over its bound")
    _holds(frame.image.ndim == 3 and frame.image.shape[2] == 3, f"image of shape {frame.image.shape}")


def _ros_seeds() -> list[bytes]:
    import numpy as np
    from gcdtrav.schemas.images import encode_jpeg
    from gcdtrav.service.ros import cdr as ros

    types = ros.typestore().types
    header = ros.make_header(12.5, "camera")
    pixels = np.random.default_rng(1).integers(0, 255, size=(6, 8, 3), dtype=np.uint8)
    image = types[ros.IMAGE](header=header, height=6, width=8, encoding="rgb8", is_bigendian=0, step=24,
                             data=pixels.ravel())  # fmt: skip
    compressed = types[ros.COMPRESSED_IMAGE](header=header, format="jpeg",
                                             data=np.frombuffer(encode_jpeg(pixels), np.uint8))  # fmt: skip
    depth = np.array([[1000, 2500], [0, 65535]], np.uint16)
    depth_image = types[ros.IMAGE](header=header, height=2, width=2, encoding="16UC1", is_bigendian=0, step=4,
                                   data=depth.view(np.uint8).ravel())  # fmt: skip
    return [
        b"\x00" + bytes(ros.typestore().serialize_cdr(image, ros.IMAGE)),
        b"\x01" + bytes(ros.typestore().serialize_cdr(compressed, ros.COMPRESSED_IMAGE)),
        b"\x02" + bytes(ros.typestore().serialize_cdr(depth_image, ros.IMAGE)),
        b"\x03" + bytes(ros.typestore().serialize_cdr(_camera_info(types, header), "sensor_msgs/msg/CameraInfo")),
        b"\x04" + bytes(ros.typestore().serialize_cdr(_odometry(types, header), "nav_msgs/msg/Odometry")),
    ]


def _camera_info(types: Any, header: Any) -> Any:
    import numpy as np

    roi = types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return types["sensor_msgs/msg/CameraInfo"](
        header=header, height=480, width=640, distortion_model="plumb_bob", d=np.zeros(5),
        k=np.array([500.0, 0, 320, 0, 510.0, 240, 0, 0, 1]), r=np.eye(3).ravel(), p=np.zeros(12),
        binning_x=0, binning_y=0, roi=roi,
    )  # fmt: skip


def _odometry(types: Any, header: Any) -> Any:
    import numpy as np

    point, quaternion = types["geometry_msgs/msg/Point"], types["geometry_msgs/msg/Quaternion"]
    pose = types["geometry_msgs/msg/Pose"](position=point(x=1.0, y=2.0, z=0.0),
                                           orientation=quaternion(x=0.0, y=0.0, z=0.0, w=1.0))  # fmt: skip
    vector = types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    twist = types["geometry_msgs/msg/Twist"](linear=vector, angular=vector)
    return types["nav_msgs/msg/Odometry"](
        header=header, child_frame_id="base_link",
        pose=types["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
    )  # fmt: skip


def _decode_ros(data: bytes) -> None:
    from gcdtrav.schemas.limits import MAX_FRAME_ID_CHARS, MAX_POSITION_M
    from gcdtrav.service.ros import cdr as ros
    from gcdtrav.service.ros.cdr import decode_camera_info_frame, decode_depth, decode_pose

    kind, payload = (data[0] % 5, data[1:]) if data else (0, b"")
    if kind in (0, 1):
        frame = ros.decode_ros_image(payload, ros.IMAGE if kind == 0 else ros.COMPRESSED_IMAGE, 4_000_000)
        _holds(len(frame.frame_id) <= MAX_FRAME_ID_CHARS, "frame_id over its bound")
    elif kind == 2:
        decode_depth(payload)
    elif kind == 3:
        camera, _ = decode_camera_info_frame(payload)
        _holds(min(camera.fx, camera.fy) > 0 and math.isfinite(camera.fx + camera.fy + camera.cx + camera.cy),
               "intrinsics not finite and positive")  # fmt: skip
    else:
        pose = decode_pose(payload, "odometry")
        _holds(max(abs(pose.x), abs(pose.y)) <= MAX_POSITION_M and math.isfinite(pose.yaw), "pose out of bounds")
        _holds(len(pose.frame_id) <= MAX_FRAME_ID_CHARS, "frame_id over its bound")


class BrokenBound(Exception):
    """A decoder accepted what it should have refused: counted as a crash."""


def _holds(condition: bool, what: str) -> None:
    if not condition:
        raise BrokenBound(f"accepted: {what}")


def _anchor_seeds() -> list[bytes]:
    from gcdtrav.schemas.anchors import default_anchor_set

    yaml_text = "name: puddles\ndefault_width: 0.05\nanchors:\n  - {concept: puddle, position: 0.0}\n"
    return [default_anchor_set().to_json().encode(), yaml_text.encode() + b"  - concept: road\n    position: 1\n"]


def _parse_anchor_document(data: bytes) -> None:
    from gcdtrav.schemas.anchors import AnchorSet

    AnchorSet.from_text(data[:65_536])  # the service refuses larger bodies before parsing


_HISTORY: Any = None


def _selector_seeds() -> list[bytes]:
    return [b"x=40;y=30", b"i=3;j=4;seq=0", b"region=0,0,20,10", b"x=1;y=2;stamp=1.0", b"x=1;x=2;y=1"]


def _answer_selector(data: bytes) -> None:
    import numpy as np
    from gcdtrav.schemas.anchors import default_anchor_set
    from gcdtrav.service.runtime.history import FrameHistory, FrameRecord
    from gcdtrav.service.runtime.queries import PATCH_FORMS, answer_patch_query, parameter_pairs, strict_parameters

    global _HISTORY
    if _HISTORY is None:
        _HISTORY = FrameHistory(depth=2)
        weights = np.full((13, 12, 16), 1 / 13, np.float16)
        _HISTORY.add("cam", FrameRecord(0, 1.0, "cam", weights, default_anchor_set(), (80, 60)))
    text = data.decode("utf-8", errors="replace")
    answer_patch_query(_HISTORY, "cam", strict_parameters(parameter_pairs(text), PATCH_FORMS))


TARGETS: dict[str, tuple[Callable[[], list[bytes]], Callable[[bytes], None], str]] = {
    "image_payloads": (_image_seeds, _decode_image, "JPEG/PNG bytes and the image envelope (msgpack)"),
    "ros_cdr": (_ros_seeds, _decode_ros, "ROS CDR Image, CompressedImage, depth, CameraInfo, Odometry"),
    "anchor_documents": (_anchor_seeds, _parse_anchor_document, "anchor-set JSON/YAML documents"),
    "selectors": (_selector_seeds, _answer_selector, "patch query selectors"),
}


def expected_errors() -> tuple[type[BaseException], ...]:
    """The decoders' own error types: a clear rejection, never a crash."""
    from gcdtrav.schemas.anchors import AnchorSetError
    from gcdtrav.schemas.inputs import RejectedInput
    from gcdtrav.schemas.messages import MessageError
    from gcdtrav.service.runtime.errors import QueryError

    return (AnchorSetError, MessageError, RejectedInput, QueryError)


def reason_of(err: BaseException) -> str:
    """A rejection's reason: its code where it has one, else the kind of its message."""
    code = getattr(err, "reason", None)
    return code if isinstance(code, str) else message_kind(str(err))


def message_kind(text: str) -> str:
    """A message with what the input put in it blanked (quoted and bracketed parts, numbers, values after
    '=' or after a second ':'), cut to its first words: messages that differ only in the input count once."""
    text = re.sub(r"'[^']*'|\"[^\"]*\"|\[[^\]]*\]|\([^)]*\)|=\S*|\d+(\.\d+)?", "#", text)
    head = ":".join(text.split(":")[:3])  # 'invalid anchor set: not valid JSON or YAML: <the parser's text>'
    return " ".join(head.split()[:10])


# ---- one target, in a child process under atheris ------------------------------------------------------


def run_target(name: str, engine: str, runs: int, out: Path, crash_dir: Path) -> None:
    seeds, call, _ = TARGETS[name]
    expected = expected_errors()
    stats: dict[str, Any] = {"inputs": 0, "reasons": Counter(), "crashes": Counter(), "hangs": 0, "slowest_s": 0.0}

    def flush() -> None:
        stats["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024  # kB on Linux
        out.write_text(json.dumps(stats | {"reasons": dict(stats["reasons"]), "crashes": dict(stats["crashes"])}))

    def one_input(data: bytes) -> None:
        began = time.perf_counter()
        try:
            call(data)
        except expected as err:
            stats["reasons"][reason_of(err)] += 1
        except Exception as err:  # a crash: kept with its input, and the campaign goes on
            kind = f"{type(err).__name__}: {str(err)[:80]}"
            if kind not in stats["crashes"]:
                (crash_dir / f"{name}-{len(stats['crashes'])}.bin").write_bytes(data)
            stats["crashes"][kind] += 1
        took = time.perf_counter() - began
        stats["slowest_s"] = max(stats["slowest_s"], took)
        stats["hangs"] += took > HANG_S
        stats["inputs"] += 1
        if stats["inputs"] % FLUSH_EVERY == 0 or stats["inputs"] >= runs - FLUSH_EVERY:
            flush()

    flush()
    if engine == "atheris":
        _fuzz_with_atheris(name, seeds(), runs, one_input)
    else:
        _fuzz_with_hypothesis(seeds(), runs, one_input)
    flush()


def _fuzz_with_atheris(name: str, seeds: list[bytes], runs: int, one_input: Callable[[bytes], None]) -> None:
    import atheris

    corpus = Path(tempfile.mkdtemp(prefix=f"fuzz-{name}-"))
    for index, seed in enumerate(seeds):
        (corpus / f"seed{index}").write_bytes(seed)
    # libFuzzer ends the process itself after -runs inputs (seeds included), without Python's exit handlers:
    # hence the periodic flush and the final one from the last input.
    atheris.Setup([sys.argv[0], f"-runs={runs}", "-max_len=65536", "-timeout=60", str(corpus)], one_input)
    atheris.instrument_all()
    atheris.Fuzz()


def _fuzz_with_hypothesis(seeds: list[bytes], runs: int, one_input: Callable[[bytes], None]) -> None:
    """Random bytes, and valid seeds with random cuts and insertions: what libFuzzer does, without coverage."""
    from hypothesis import HealthCheck, Phase, given, settings
    from hypothesis import strategies as st

    edits = st.lists(st.tuples(st.integers(0, 1 << 16), st.integers(0, 32), st.binary(max_size=32)), max_size=8)
    mutated = st.tuples(st.sampled_from(seeds), edits).map(lambda pair: _edited(*pair))

    @settings(max_examples=runs, database=None, deadline=None, phases=[Phase.generate],
              suppress_health_check=list(HealthCheck))  # fmt: skip
    @given(st.one_of(mutated, st.binary(max_size=4096)))
    def fuzz(data: bytes) -> None:
        one_input(data)

    fuzz()


def _edited(seed: bytes, edits: list[tuple[int, int, bytes]]) -> bytes:
    data = bytearray(seed)
    for at, cut, insert in edits:
        at %= len(data) + 1
        data[at : at + cut] = insert
    return bytes(data)


# ---- the campaign ---------------------------------------------------------------------------------


def campaign(targets: list[str], engine: str, runs: int, max_seconds: float, out: Path) -> dict[str, Any]:
    crash_dir = out.parent / "fuzz-crashes"
    crash_dir.mkdir(parents=True, exist_ok=True)
    results: dict[str, Any] = {}
    for name in targets:
        part = Path(tempfile.mkstemp(suffix=f"-{name}.json")[1])
        command = [sys.executable, __file__, "--child", name, "--engine", engine, "--runs", str(runs)]
        command += ["--part", str(part)]
        command += ["--crash-dir", str(crash_dir)]
        began = time.monotonic()
        child = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        try:
            _, stderr = child.communicate(timeout=max_seconds)
            status, timed_out = child.returncode, False
        except subprocess.TimeoutExpired:
            child.kill()
            _, stderr = child.communicate()
            status, timed_out = child.returncode, True
        stats = json.loads(part.read_text()) if part.stat().st_size else {"inputs": 0}
        part.unlink()
        results[name] = {
            "what": TARGETS[name][2],
            "inputs": stats.get("inputs", 0),
            "distinct_reasons": len(stats.get("reasons", {})),
            "reasons": dict(sorted(stats.get("reasons", {}).items(), key=lambda kv: -kv[1])),
            "crashes": sum(stats.get("crashes", {}).values()),
            "crash_kinds": stats.get("crashes", {}),
            "hangs_over_1s": stats.get("hangs", 0),
            "slowest_s": round(stats.get("slowest_s", 0.0), 3),
            "peak_rss_mb": stats.get("peak_rss_mb"),
            "seconds": round(time.monotonic() - began, 1),
            "stopped_by": "time limit" if timed_out else f"input count (exit {status})",
        }
        if status not in (0, None) and not timed_out:  # a crash of the interpreter itself, not of a decoder
            results[name]["stderr_tail"] = (stderr or "")[-2000:]
        print(f"  {name}: {results[name]['inputs']} inputs, {results[name]['crashes']} crashes", file=sys.stderr)
    return results


ENGINES = {
    "atheris": "atheris (libFuzzer), coverage-guided",
    "hypothesis": "hypothesis: random bytes and random edits of valid seeds, not coverage-guided",
}


def _installed(module: str) -> bool:
    import importlib.util

    return importlib.util.find_spec(module) is not None


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=100_000, help="inputs per target [100000]")
    parser.add_argument("--max-seconds", type=float, default=900.0, help="time limit per target [900]")
    parser.add_argument("--targets", nargs="+", choices=sorted(TARGETS), default=list(TARGETS))
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/fuzz.json"))
    parser.add_argument("--engine", choices=("auto", "atheris", "hypothesis"), default="auto",
                        help="auto: atheris where it is installed, else hypothesis [auto]")  # fmt: skip
    parser.add_argument("--child", choices=sorted(TARGETS), help=argparse.SUPPRESS)
    parser.add_argument("--part", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--crash-dir", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    engine = args.engine if args.engine != "auto" else ("atheris" if _installed("atheris") else "hypothesis")
    if args.child:
        run_target(args.child, engine, args.runs, args.part, args.crash_dir)
        return 0
    if engine == "atheris" and not _installed("atheris"):
        print("benchmarks/fuzz.py --engine atheris needs atheris: pip install atheris", file=sys.stderr)
        return 2
    label = ENGINES[engine]
    print(f"fuzzing {len(args.targets)} targets, {args.runs} inputs each ({label})", file=sys.stderr)
    results = campaign(args.targets, engine, args.runs, args.max_seconds, args.out)
    report = {"engine": label, "runs_per_target": args.runs, "targets": results}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print("| target | inputs | distinct reasons | crashes | hangs > 1 s | slowest s | peak RSS MB |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for name, r in results.items():
        print(
            f"| {name} | {r['inputs']} | {r['distinct_reasons']} | {r['crashes']} | {r['hangs_over_1s']} | "
            f"{r['slowest_s']} | {r['peak_rss_mb']} |"
        )
    print(f"written: {args.out}")
    return 1 if any(r["crashes"] for r in results.values()) else 0


if __name__ == "__main__":
    sys.exit(main())
