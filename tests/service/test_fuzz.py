"""Fuzz every decoder the service exposes: no crash, no hang, a clear error each time.

Each property runs ``EXAMPLES`` generated inputs (hypothesis); the only exceptions allowed are the
decoders' own error types, whose messages must say something.
"""

from __future__ import annotations

import json

import msgpack
import numpy as np
import pytest
from gcdtrav.schemas.anchors import AnchorSet, AnchorSetError, default_anchor_set
from gcdtrav.schemas.images import encode_jpeg, encode_png
from gcdtrav.schemas.inputs import RejectedInput, decode_payload
from gcdtrav.schemas.messages import ImageEnvelope, MessageError, PixelEncoding
from gcdtrav.service.runtime.errors import QueryError
from gcdtrav.service.runtime.history import FrameHistory, FrameRecord
from gcdtrav.service.runtime.queries import answer_patch_query
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

EXAMPLES = 500
FUZZ = settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
LIMITS = {"received_at": 0.0, "max_bytes": 2_000_000, "max_pixels": 4_000_000}
SMALL = np.random.default_rng(0).integers(0, 255, size=(12, 16, 3), dtype=np.uint8)
SEEDS = [
    encode_png(SMALL),
    encode_jpeg(SMALL),
    ImageEnvelope(stamp=1.0, encoding=PixelEncoding.RGB8, width=16, height=12, data=SMALL.tobytes()).pack(),
]


def mutated(seed: bytes, data: st.DataObject) -> bytes:
    """A valid payload with bytes flipped, cut or spliced: reaches deeper than random bytes."""
    buffer = bytearray(seed)
    for _ in range(data.draw(st.integers(1, 8))):
        action = data.draw(st.sampled_from(["flip", "cut", "insert"]))
        position = data.draw(st.integers(0, max(len(buffer) - 1, 0)))
        if action == "flip" and buffer:
            buffer[position] ^= data.draw(st.integers(1, 255))
        elif action == "cut":
            del buffer[position : position + data.draw(st.integers(1, 64))]
        else:
            buffer[position:position] = data.draw(st.binary(min_size=1, max_size=16))
    return bytes(buffer)


def check_decode(payload: bytes, encoding: str) -> None:
    try:
        frame = decode_payload(payload, encoding, **LIMITS)
    except RejectedInput as err:
        assert err.reason and err.detail
        return
    assert frame.image.dtype == np.uint8 and frame.image.ndim == 3 and frame.image.shape[2] == 3


@FUZZ
@given(
    payload=st.binary(max_size=4096),
    encoding=st.sampled_from(["", "image/jpeg", "image/png", "application/msgpack", "text/plain"]),
)
def test_image_payloads_random_bytes(payload: bytes, encoding: str) -> None:
    check_decode(payload, encoding)


@FUZZ
@given(data=st.data(), seed=st.sampled_from(SEEDS))
def test_image_payloads_mutated(data: st.DataObject, seed: bytes) -> None:
    encoding = "application/msgpack" if seed is SEEDS[2] else ""
    check_decode(mutated(seed, data), encoding)


INT64 = st.integers(-(2**63), 2**63 - 1)  # what msgpack can carry
envelope_fields = st.fixed_dictionaries(
    {},
    optional={
        "stamp": st.one_of(st.floats(allow_nan=True), INT64, st.text(max_size=5), st.none()),
        "frame_id": st.one_of(st.text(max_size=20), INT64, st.binary(max_size=5)),
        "encoding": st.one_of(st.sampled_from(["rgb8", "bgr8", "mono8", "jpeg", "png", "yuv", ""]), INT64),
        "width": st.one_of(st.integers(-5, 70000), st.floats(allow_nan=True), st.text(max_size=3)),
        "height": st.one_of(st.integers(-5, 70000), st.floats(allow_nan=True)),
        "data": st.one_of(st.binary(max_size=2048), st.text(max_size=10), INT64),
        "extra": INT64,
    },
)


@FUZZ
@given(fields=envelope_fields)
def test_envelopes_with_any_fields(fields: dict) -> None:
    check_decode(msgpack.packb(fields, use_bin_type=True), "application/msgpack")


def history_with_one_frame() -> FrameHistory:
    history = FrameHistory(depth=2)
    weights = np.full((13, 8, 10), 1 / 13, dtype=np.float16)
    history.add(
        "cam",
        FrameRecord(
            seq=0, stamp=5.0, frame_id="f", weights=weights, anchors=default_anchor_set(), image_size=(100, 80)
        ),
    )
    return history


HISTORY = history_with_one_frame()
parameter_values = st.one_of(
    st.text(max_size=30),
    st.integers(-(10**9), 10**9).map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(str),
    st.lists(st.floats(-200, 200), min_size=0, max_size=6).map(lambda v: ",".join(map(str, v))),
)


@FUZZ
@given(
    params=st.dictionaries(st.sampled_from(["x", "y", "i", "j", "seq", "stamp", "region", "zzz"]), parameter_values),
    source=st.sampled_from(["cam", "other", ""]),
)
def test_patch_query_parameters(params: dict[str, str], source: str) -> None:
    try:
        reply = answer_patch_query(HISTORY, source, params)
    except QueryError as err:
        assert str(err)
        return
    assert abs(sum(reply.weights) - 1.0) < 1e-3 and 0.0 <= reply.mean <= 1.0


anchor_like = st.recursive(
    st.one_of(st.none(), st.booleans(), st.floats(allow_nan=True), st.integers(), st.text(max_size=12)),
    lambda children: st.one_of(
        st.lists(children, max_size=5),
        st.dictionaries(
            st.sampled_from(["anchors", "concept", "position", "width", "name", "default_width", "x"]),
            children,
            max_size=5,
        ),
    ),
    max_leaves=30,
)


@FUZZ
@given(document=anchor_like)
def test_anchor_set_payloads_structured(document: object) -> None:
    try:
        text = json.dumps(document)
    except ValueError:
        return
    try:
        AnchorSet.from_text(text)
    except AnchorSetError as err:
        assert err.messages and all(isinstance(m, str) and m for m in err.messages)


@FUZZ
@given(payload=st.binary(max_size=512))
def test_anchor_set_payloads_random_bytes(payload: bytes) -> None:
    try:
        AnchorSet.from_text(payload)
    except AnchorSetError as err:
        assert err.messages


@FUZZ
@given(payload=st.binary(max_size=1024))
def test_message_unpack_random_bytes(payload: bytes) -> None:
    try:
        ImageEnvelope.unpack(payload)
    except MessageError as err:
        assert str(err)


@FUZZ
@given(data=st.data(), msgtype=st.sampled_from(["sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"]))
def test_ros_cdr_payloads_mutated(data: st.DataObject, msgtype: str) -> None:
    ros = pytest.importorskip("gcdtrav.service.ros.cdr")
    if msgtype == ros.IMAGE:
        message = ros.typestore().types[ros.IMAGE](
            header=ros.make_header(1.5, "cam"),
            height=12,
            width=16,
            encoding="rgb8",
            is_bigendian=0,
            step=48,
            data=SMALL.ravel(),
        )
    else:
        message = ros.typestore().types[ros.COMPRESSED_IMAGE](
            header=ros.make_header(1.5, "cam"), format="png", data=np.frombuffer(SEEDS[0], np.uint8)
        )
    seed = bytes(ros.typestore().serialize_cdr(message, msgtype))
    try:
        frame = ros.decode_ros_image(mutated(seed, data), msgtype, 4_000_000)
    except ros.RejectedInput as err:
        assert err.reason and err.detail
        return
    assert frame.image.dtype == np.uint8 and frame.image.shape[2] == 3
