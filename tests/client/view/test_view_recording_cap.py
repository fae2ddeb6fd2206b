"""`gcdtrav view --record DIR --record-max-mb N`: files rotate, and the oldest files of the recording are
deleted to keep it under the cap; what is kept is the newest data, every file readable."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

foxglove = pytest.importorskip("foxglove", reason="the view extra: pip install 'gcdtrav[view]'")
mcap_reader = pytest.importorskip("mcap.reader")

from gcdtrav.client.commands.view import RECORD_MAX_MB, megabytes, usage_problem  # noqa: E402
from gcdtrav.client.view.recorder import FILES_UNDER_CAP, McapRecorder  # noqa: E402
from gcdtrav.service.commands.cli import build_parser  # noqa: E402

CAP = 96 * 1024
MESSAGE_BYTES = 3000  # random, so zstd cannot shrink it


def record(directory: Path, messages: int) -> McapRecorder:
    context = foxglove.Context()
    channel = foxglove.Channel("/noise", schema={"type": "object", "title": "noise"}, context=context)
    recorder = McapRecorder(directory, context, file_bytes=256 * 1024 * 1024, total_bytes=CAP)
    rng = np.random.default_rng(0)
    for index in range(messages):
        channel.log({"index": index, "noise": rng.bytes(MESSAGE_BYTES).hex()[:MESSAGE_BYTES]})
        recorder.rotate_if_full()
    recorder.close()
    return recorder


def indexes_in(path: Path) -> list[int]:
    with path.open("rb") as stream:
        reader = mcap_reader.make_reader(stream)
        assert reader.get_summary() is not None, f"{path} was not closed cleanly"
        return [json.loads(message.data)["index"] for _, _, message in reader.iter_messages()]


def test_the_oldest_files_go_and_the_newest_data_stays_under_the_cap(tmp_path: Path) -> None:
    foreign = tmp_path / "someone-elses.mcap"
    foreign.write_bytes(b"not ours")
    recorder = record(tmp_path, messages=300)  # about 900 kB through a 96 kB cap

    assert recorder.file_bytes == CAP // FILES_UNDER_CAP  # the per-file size follows the small cap
    assert len(recorder.deleted) > 10 and not any(path.exists() for path in recorder.deleted)
    assert foreign.read_bytes() == b"not ours"  # only the recorder's own files are deleted
    kept = sorted(tmp_path.glob("gcdtrav-*.mcap"))
    assert kept == sorted(recorder.files) and len(kept) >= FILES_UNDER_CAP - 1
    total = sum(path.stat().st_size for path in kept)
    assert total <= CAP + 16 * 1024 + MESSAGE_BYTES, total  # the cap, passed by at most a chunk and a message
    indexes = [index for path in recorder.files for index in indexes_in(path)]
    assert indexes == list(range(indexes[0], 300)) and indexes[0] > 0  # the newest, contiguous, none twice


def test_recordings_are_capped_by_default_and_0_means_no_limit() -> None:
    parse = build_parser().parse_args
    assert parse(["view"]).record_max_mb == RECORD_MAX_MB == 4096 and parse(["view"]).record_file_mb == 256
    assert parse(["view", "--record-max-mb", "0"]).record_max_mb == 0
    negative = usage_problem(parse(["view", "--record-max-mb", "-1"]))
    assert negative == "--record-max-mb must be positive (or 0: no limit)"
    assert usage_problem(parse(["view", "--record-max-mb", "512"])) is None and megabytes(0.5) == 512 * 1024
    assert parse(["view"]).record_camera_every == 1
    assert usage_problem(parse(["view", "--record-camera-every", "-1"])) is not None
    assert usage_problem(parse(["view", "--record-camera-every", "0"])) is None


def camera_payload(seq: int) -> bytes:
    """A camera frame as robots send it: an envelope holding a JPEG, stamped 100 + seq."""
    import cv2
    from gcdtrav.schemas.messages import ImageEnvelope, PixelEncoding

    jpeg = cv2.imencode(".jpg", np.full((8, 8, 3), seq, np.uint8))[1].tobytes()
    envelope = ImageEnvelope(stamp=100.0 + seq, frame_id="front", encoding=PixelEncoding.JPEG, width=8, height=8,
                             data=jpeg)  # fmt: skip
    return envelope.pack()


def recorded_camera_stamps(viewer_options: dict[str, object], tmp_path: Path, frames: int = 10) -> list[int]:
    from gcdtrav.client.view.viewer import Viewer, ViewOptions
    from view_fakes import FakeClient, maps_payload
    from zenoh_helpers import wait_until

    client = FakeClient()
    options = ViewOptions(port=0, record=tmp_path, status_period_s=30.0, **viewer_options)  # type: ignore[arg-type]
    with Viewer(client, options) as viewer:  # type: ignore[arg-type]
        client.session.put("gcdtrav/out/cam/maps", maps_payload("cam", (4, 4), (8, 8)))
        for seq in range(frames):
            client.session.put("gcdtrav/in/cam", camera_payload(seq))
            assert wait_until(lambda n=seq + 1: viewer.logged["/gcdtrav/cam/camera"] >= n, 30)
        files = list(viewer.recorder.files) if viewer.recorder else []
    stamps = []
    for path in files:
        with path.open("rb") as stream:
            for _, channel, message in mcap_reader.make_reader(stream).iter_messages():
                if channel.topic == "/gcdtrav/cam/camera":
                    stamps.append(message.publish_time or message.log_time)
        with path.open("rb") as stream:
            topics = {channel.topic for _, channel, _ in mcap_reader.make_reader(stream).iter_messages()}
        assert "/gcdtrav/cam/traversability" in topics  # the other channels are recorded whatever the camera
    return stamps


def test_the_camera_is_recorded_whole_one_in_n_or_not_at_all(tmp_path: Path) -> None:
    assert len(recorded_camera_stamps({}, tmp_path / "all")) == 10
    assert len(recorded_camera_stamps({"record_camera_every": 3}, tmp_path / "third")) == 4  # frames 0, 3, 6, 9
    assert recorded_camera_stamps({"record_camera_every": 0}, tmp_path / "none") == []
