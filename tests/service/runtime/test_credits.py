"""Credits without zenoh: the grants a source's owner publishes; the times read at intake."""

from __future__ import annotations

import msgpack
import pytest
from gcdtrav.schemas.messages import CreditGrant, ImageEnvelope
from gcdtrav.schemas.messages.credits import REFUSED, STALE, TAKEN
from gcdtrav.schemas.ros_image import peek_stamp
from gcdtrav.service.runtime.fleet.credits import CreditLedger
from gcdtrav.service.runtime.frames import FrameTimes
from gcdtrav.service.runtime.intake.frame_age import input_times

from tools.ros_fixtures import compressed_image_cdr


def ledger(**kw: object) -> CreditLedger:
    return CreditLedger("box-1", (352, 352), 5.0, clock=lambda: 100.0, **kw)  # type: ignore[arg-type]


def test_grants_are_numbered_per_source_and_describe_the_freed_frame() -> None:
    credits = ledger()
    first = credits.freed("r1/front", TAKEN, FrameTimes(stamp=98.0, sent_at=98.5, received_at=99.0))
    assert (first.source, first.instance, first.grant, first.reason) == ("r1/front", "box-1", 0, "taken")
    assert (first.frame_stamp, first.frame_sent_at, first.frame_received_at) == (98.0, 98.5, 99.0)
    assert (first.granted_at, first.model_input, first.max_frame_age_s, first.last_maps_stamp) == (
        100.0,
        (352, 352),
        5.0,
        None,
    )
    assert credits.freed("r1/front", STALE).grant == 1
    assert credits.freed("r2/front", REFUSED).grant == 0  # each source counts its own
    assert credits.freed("r1/front", TAKEN).grant == 2 and credits.freed("nobody", TAKEN).grant == 0


def test_a_grant_says_how_fresh_the_published_maps_are() -> None:
    credits = ledger()
    credits.published("cam", 50.0)
    credits.published("cam", 40.0)  # out of order: the newest stays
    assert credits.freed("cam", TAKEN).last_maps_stamp == 50.0
    credits.forget("cam")
    grant = credits.freed("cam", TAKEN)
    assert grant.grant == 0 and grant.last_maps_stamp is None


def test_a_grant_survives_the_wire() -> None:
    grant = ledger().freed("a/b", TAKEN, FrameTimes(1.0, None, 2.0))
    assert CreditGrant.unpack(grant.pack()) == grant


# ---- what is read at intake ---------------------------------------------------------------------


def test_input_times_read_without_decoding() -> None:
    envelope = ImageEnvelope(stamp=12.5, encoding="jpeg", width=1, height=1, data=b"\xff" * 1000, sent_at=13.0)
    times = input_times(envelope.pack(), "application/msgpack", ros=False)
    assert (times.stamp, times.sent_at) == (12.5, 13.0)
    older = {k: v for k, v in envelope.model_dump().items() if k != "sent_at"}  # a sender before 1.1's relay
    times = input_times(msgpack.packb(older, use_bin_type=True), "", ros=False)  # found by content
    assert (times.stamp, times.sent_at) == (12.5, None)
    assert input_times(b"\xff\xd8\xff\xe0jpeg", "image/jpeg", ros=False).stamp is None
    assert input_times(b"\x81\xa5stamp\xa3bad", "", ros=False).stamp is None  # a string: no stamp
    assert input_times(b"\xde\x00", "", ros=False).stamp is None  # truncated msgpack: the decoder will say why
    assert input_times(compressed_image_cdr(b"\xff\xd8", 7.25), "", ros=True).stamp == pytest.approx(7.25)
    assert peek_stamp(b"\x00\x01\x00\x00\x01") is None  # truncated
    assert peek_stamp(b"garbage-garbage-") is None
