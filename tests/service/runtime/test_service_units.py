"""Parts of the service that need no bus: queue, payload decoding, settings, state file, key mapping."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import textured_image
from gcdtrav.schemas.anchors import default_anchor_set
from gcdtrav.schemas.images import encode_jpeg, encode_png
from gcdtrav.schemas.inputs import RejectedInput, decode_payload
from gcdtrav.schemas.keys import input_source_of, literal_head
from gcdtrav.schemas.messages import ImageEnvelope, MapsMessage, MessageError, PixelEncoding
from gcdtrav.schemas.settings import SettingsError, load_settings
from gcdtrav.service.runtime.schedule.latest_queue import LatestFrameQueue

LIMITS = {"received_at": 1.0, "max_bytes": 10_000_000, "max_pixels": 10_000_000}


def test_latest_only_keeps_newest_and_counts_drops() -> None:
    queue: LatestFrameQueue[int] = LatestFrameQueue()
    for value in range(5):
        queue.put("fast", value)
    assert len(queue) == 1
    assert queue.take(0) == ("fast", 4)
    counters = queue.counters()["fast"]
    assert (counters.received, counters.dropped) == (5, 4)
    assert queue.take(0.01) is None


def test_round_robin_does_not_starve_slow_sources() -> None:
    queue: LatestFrameQueue[int] = LatestFrameQueue()
    served = []
    queue.put("slow", 0)
    for step in range(30):
        queue.put("fast", step)  # the fast robot always has a new frame waiting
        if step % 10 == 0:
            queue.put("slow", step)
        item = queue.take(0)
        assert item is not None
        served.append(item[0])
    assert served.count("slow") >= 3
    assert served[:2] == ["slow", "fast"]


def test_take_returns_none_after_close() -> None:
    queue: LatestFrameQueue[int] = LatestFrameQueue()
    queue.close()
    assert queue.take(5) is None


def test_key_mapping() -> None:
    assert literal_head("gcdtrav/in/**") == "gcdtrav/in"
    assert literal_head("robot/*/camera/*/image") == "robot"
    assert input_source_of("gcdtrav/in/r1/front", "gcdtrav/in") == "r1/front"
    assert input_source_of("robot/r2/camera/left/image", "robot") == "r2/camera/left/image"
    assert input_source_of("cam/front", literal_head("cam/front")) == "cam/front"


@pytest.mark.parametrize("encoding", ["jpeg", "png", "rgb8", "bgr8", "mono8"])
def test_envelopes_decode_to_rgb(encoding: str) -> None:
    image = textured_image(30, 40)
    data = {
        "jpeg": encode_jpeg(image, 95),
        "png": encode_png(image),
        "rgb8": image.tobytes(),
        "bgr8": image[:, :, ::-1].copy().tobytes(),
        "mono8": image[:, :, 1].copy().tobytes(),
    }[encoding]
    envelope = ImageEnvelope(
        stamp=12.5, frame_id="cam", encoding=PixelEncoding(encoding), width=40, height=30, data=data
    )
    frame = decode_payload(envelope.pack(), "application/msgpack", **LIMITS)
    assert frame.stamp == 12.5 and frame.frame_id == "cam" and frame.image.shape == (30, 40, 3)
    if encoding in ("png", "rgb8", "bgr8"):
        np.testing.assert_array_equal(frame.image, image)
    elif encoding == "mono8":
        np.testing.assert_array_equal(frame.image[:, :, 0], image[:, :, 1])
    else:  # JPEG is lossy: compare with OpenCV's own decoding, channel order included
        expected = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)[:, :, ::-1]
        np.testing.assert_array_equal(frame.image, expected)


def test_bare_image_bytes_use_receive_time() -> None:
    frame = decode_payload(encode_png(textured_image(8, 8)), "image/png", **LIMITS)
    assert frame.stamp == 1.0 and frame.frame_id == ""


@pytest.mark.parametrize(
    ("payload", "encoding", "reason"),
    [
        (b"", "image/jpeg", "empty"),
        (b"\xff\xd8\xff\xe0 broken jpeg", "image/jpeg", "undecodable"),
        (b"GARBAGE!" * 400, "", "undecodable"),
        (b"\x81\xa1a\x01", "application/msgpack", "malformed_envelope"),
        (b"\x93\x01\x02\x03", "application/msgpack", "malformed_envelope"),
        (b"\xc1\xc1", "application/msgpack", "malformed_envelope"),
        (
            ImageEnvelope(stamp=0, encoding=PixelEncoding.RGB8, width=4, height=4, data=b"123").pack(),
            "application/msgpack",
            "size_mismatch",
        ),
        (
            ImageEnvelope(stamp=0, encoding=PixelEncoding.RGB8, width=10**5, height=10**5, data=b"").pack(),
            "application/msgpack",
            "too_many_pixels",
        ),
        (
            ImageEnvelope(stamp=0, encoding=PixelEncoding.JPEG, width=4, height=4, data=b"nope").pack(),
            "application/msgpack",
            "undecodable",
        ),
    ],
)
def test_bad_payloads_are_rejected_with_a_reason(payload: bytes, encoding: str, reason: str) -> None:
    with pytest.raises(RejectedInput) as info:
        decode_payload(payload, encoding, **LIMITS)
    assert info.value.reason == reason


def test_byte_and_pixel_limits_checked_before_decoding(monkeypatch: pytest.MonkeyPatch) -> None:
    calls = []
    monkeypatch.setattr(cv2, "imdecode", lambda *a: calls.append(1))
    big = encode_png(np.zeros((200, 300, 3), np.uint8))
    with pytest.raises(RejectedInput, match="oversized"):
        decode_payload(big, "image/png", 1.0, max_bytes=100, max_pixels=10**9)
    with pytest.raises(RejectedInput, match="too_many_pixels"):
        decode_payload(big, "image/png", 1.0, max_bytes=10**9, max_pixels=1000)
    assert calls == []


def test_message_unpack_rejects_wrong_shapes() -> None:
    with pytest.raises(MessageError, match="msgpack map"):
        MapsMessage.unpack(b"\x01")
    with pytest.raises(MessageError, match="invalid MapsMessage"):
        MapsMessage.unpack(b"\x80")


def test_settings_layers(tmp_path: Path) -> None:
    file = tmp_path / "service.yaml"
    file.write_text("prefix: fleet/a\nhistory: 4\ninputs: ['robot/*/camera/*/image']\nengine: {method: argmax}\n")
    env = {"GCDTRAV_HISTORY": "6", "GCDTRAV_ENGINE__TEMPERATURE": "0.5", "OTHER": "x"}
    settings = load_settings(file, {"instance": "box1", "model": None}, environ=env)
    assert settings.prefix == "fleet/a" and settings.history == 6 and settings.instance == "box1"
    assert settings.engine.method.value == "argmax" and settings.engine.temperature == 0.5
    assert settings.inputs == ["robot/*/camera/*/image"]
    assert load_settings(None, None, environ={"GCDTRAV_INPUTS": "a/**, b/*"}).inputs == ["a/**", "b/*"]


def test_settings_reject_unknown_and_invalid(tmp_path: Path) -> None:
    file = tmp_path / "service.yaml"
    file.write_text("prefx: typo\n")
    with pytest.raises(SettingsError, match="prefx"):
        load_settings(file, environ={})
    with pytest.raises(SettingsError, match="history"):
        load_settings(None, {"history": 0}, environ={})
    with pytest.raises(SettingsError, match="literal zenoh key"):
        load_settings(None, {"prefix": "a/*"}, environ={})
    with pytest.raises(SettingsError, match="cannot read"):
        load_settings(tmp_path / "missing.yaml", environ={})


def test_an_unusable_old_state_file_is_not_imported(tmp_path: Path) -> None:
    from gcdtrav.service.store.legacy import import_anchor_state
    from gcdtrav.service.store.sqlite import SqliteStore

    path = tmp_path / "s.json"
    path.write_text('{"anchors": []}')
    store = SqliteStore(tmp_path / "store.sqlite3")
    assert import_anchor_state(store, path, "box-1") == 0 and store.active() is None and path.is_file()
    store.close()


def test_history_numbers_frames_per_source_and_restarts_a_forgotten_one() -> None:
    from gcdtrav.service.runtime.history import FrameHistory

    anchors = default_anchor_set()
    weights = np.full((len(anchors), 2, 2), 1 / len(anchors), np.float32)
    history = FrameHistory(depth=1)  # keeps one frame per source: numbering must outlive evicted frames
    seqs = [history.record(s, weights, anchors, 1.0, "cam", (4, 4)).seq for s in ("a", "a", "b", "a")]
    assert seqs == [0, 1, 0, 2]
    assert history.get("a", None).seq == 2 and history.get("a", None).weights.dtype == np.float16
    history.forget("a")
    assert history.record("a", weights, anchors, 2.0, "cam", (4, 4)).seq == 0
    assert history.record("b", weights, anchors, 2.0, "cam", (4, 4)).seq == 1
