"""The wire rule (docs/messages.md, "Compatibility"): every message decodes with a field it does not know and
with a newer minor version, refuses another major, and configuration stays strict."""

from __future__ import annotations

from enum import Enum
from typing import Any

import msgpack
import pytest
from gcdtrav.schemas import experience as e
from gcdtrav.schemas import messages as m
from gcdtrav.schemas.anchors import AnchorSet, AnchorSetError, default_anchor_set
from gcdtrav.schemas.settings import ServiceSettings
from pydantic import BaseModel, ValidationError

ANCHORS = default_anchor_set()
MAPS_HEADER = m.MapsHeader(
    source="r1/front", key="gcdtrav/in/r1/front", seq=3, stamp=1.5, received_at=1.6, published_at=2.0,
    inference_ms=400.0, model="tiny", instance="box-1", anchor_set_version=ANCHORS.version, method="gcd",
    map_shape=(2, 2), image_size=(4, 4), scale=(2.0, 2.0), computed_from=(1.0, 2),
)  # fmt: skip
DISTRIBUTION = m.ContextDistribution(
    source="r1/front", seq=3, stamp=1.5, anchor_set_version=ANCHORS.version,
    anchors=[m.AnchorPoint(concept=a.concept, position=a.position, width=0.0) for a in ANCHORS.anchors],
    weights=[1 / len(ANCHORS)] * len(ANCHORS), patch=(0, 1), mean=0.5, std=0.2, skewness=0.0,
    excess_kurtosis=0.0, entropy=1.0, modes=2, top_anchors=[0, 1], density_x=[0.0, 1.0], density=[1.0, 1.0],
    density_bandwidth=0.025,
)  # fmt: skip
GRID_HEADER = m.GridHeader(
    source="cam", seq=1, stamp=1.0, frame_id="odom", origin=(0.0, 0.0), resolution=0.1, cells=4,
    anchor_set_version=ANCHORS.version, resets=0, known_cells=3, instance="box-1",
    alpha=0.1, tau=0.3, expired_cells=2, age_s=0.5,
)  # fmt: skip
SAMPLES: dict[type[m.Message], m.Message] = {
    m.ImageEnvelope: m.ImageEnvelope(stamp=1.0, encoding="rgb8", width=1, height=1, data=b"\0\0\0"),
    m.MapsMessage: m.MapsMessage(header=MAPS_HEADER, traversability_png=b"t", uncertainty_png=b"u"),
    m.ContextDistribution: DISTRIBUTION,
    m.Pose2D: m.Pose2D(stamp=1.0, x=1.0, y=2.0, yaw=0.5),
    m.GridMessage: m.GridMessage(
        header=GRID_HEADER,
        traversability_png=b"t",
        uncertainty_png=b"u",
        count_png=b"c",
        cvar_png=b"v",
        p_below_png=b"p",
        match_png=b"m",
        age_png=b"a",
    ),
    m.PathReply: m.PathReply(
        source="cam",
        stamp=1.0,
        anchor_set_version=ANCHORS.version,
        points=[(0, 0), (1, 1)],
        cells=[DISTRIBUTION],
        unknown_cells=0,
    ),
    m.AnchorSetReply: m.AnchorSetReply(anchor_set=ANCHORS, version=ANCHORS.version),
    m.AnchorHistoryReply: m.AnchorHistoryReply(
        instance="box-1", entries=[m.AnchorHistoryEntry(accepted_at=1.0, version=ANCHORS.version, anchor_set=ANCHORS)]
    ),
    m.AnchorSetRejection: m.AnchorSetRejection(errors=["bad"], active_version=ANCHORS.version),
    m.ErrorReply: m.ErrorReply(error="x"),
    m.ServiceStatus: m.ServiceStatus(
        instance="box-1",
        uptime_s=1.0,
        model="tiny",
        anchor_set_version=ANCHORS.version,
        method="gcd",
        queued=0,
        sources={"r1/front": m.SourceStatus(received=2, unchanged=1, weight=0.7, share=0.25)},
        rejected_by_reason={},
        last_errors=[],
        experience=m.ExperienceStatus(
            source="r1/front",
            pairs=3,
            counts={"pairs": 3},
            open_questions=[
                m.QuestionStatus(
                    id="q1",
                    source="r1/front",
                    stamp=2.0,
                    reason="ambiguous",
                    concepts=["bush", "grass"],
                    region=(0.0, 0.0, 1.0, 1.0),
                )
            ],
        ),
    ),
    m.SourceView: m.SourceView(source="r1/front", maps=MAPS_HEADER, instances={"box-1": m.SourceStatus()}),
    m.CompactMapsMessage: m.CompactMapsMessage(header=MAPS_HEADER, traversability_png=b"t", uncertainty_png=b"u"),
    m.CreditGrant: m.CreditGrant(
        source="r1/front",
        instance="box-1",
        grant=0,
        reason="taken",
        granted_at=2.0,
        model_input=(352, 352),
        max_frame_age_s=5.0,
        frame_stamp=1.0,
        frame_sent_at=1.1,
        frame_received_at=1.2,
        last_maps_stamp=0.5,
    ),
    m.RelayHealth: m.RelayHealth(
        source="r1/front",
        published_at=3.0,
        newest_map_stamp=1.0,
        map_age_s=2.0,
        stale=False,
        stale_after_s=3.0,
        frames_captured=10,
        frames_sent=2,
        credit_timeouts=0,
        uplink_bytes_per_s=1e4,
        downlink_bytes_per_s=2e4,
        parked=True,
    ),
    m.CameraParked: m.CameraParked(parked=True, reason="charging"),
}

FIGURES = e.CalibrationFigures(
    pairs=2, mae=0.1, bias=-0.05, coverage={"0.05": 1.0, "0.1": 0.5, "0.2": None}, tau=0.3,
    reliability=[e.ReliabilityBin(low=0.0, high=0.1, count=2, predicted=0.05, observed=0.0)], ece=0.05,
    ause=0.01, spearman_u_error=None,
    anchors=[e.AnchorFigures(concept="grass", position=0.5, width=0.0, weight_mass=1.5, dominant_pairs=2,
                             dominant_mean_outcome=0.8)],
)  # fmt: skip
SAMPLES.update(
    {
        e.TraversalOutcome: e.TraversalOutcome(stamp=1.0, x=1.0, y=-2.0, score=0.8, kind="velocity", radius_m=0.3),
        e.Twist2D: e.Twist2D(stamp=1.0, vx=0.5, wz=0.1),
        e.Odometry2D: e.Odometry2D(stamp=1.0, x=1.0, y=2.0, yaw=0.1, vx=0.4),
        e.CalibrationReport: e.CalibrationReport(
            source="cam", stamp=2.0, anchor_set_version=ANCHORS.version, concepts=ANCHORS.concepts,
            figures=FIGURES, pairs_by_kind={"velocity": 2}, pairs_by_version={ANCHORS.version: 2},
            counts={"outcomes": 3, "unknown_cell": 1},
        ),
        e.AnchorProposal: e.AnchorProposal(
            stamp=2.0, source="cam", current=ANCHORS, proposed=ANCHORS, current_version=ANCHORS.version,
            proposed_version=ANCHORS.version, diff=["~ grass @ 0.50 -> 0.80"],
            changes=[e.AnchorChange(concept="grass", position_before=0.5, position_after=0.8, width_before=0.0,
                                    width_after=0.05, pairs=250.0, shrunk=False)],
            train_pairs=7, held_out_pairs=3, before=FIGURES, after=FIGURES,
        ),
        e.OperatorQuestion: e.OperatorQuestion(
            id="q1", source="cam", stamp=1.0, reason="ambiguous", region=(0.0, 0.0, 1.0, 1.0), cells=[(0.5, 0.5)],
            concepts=[e.QuestionConcept(concept="grass", position=0.5, weight=0.5),
                      e.QuestionConcept(concept="bush", position=0.1, weight=0.4)],
            traversability=0.3, uncertainty=0.2, p_below=0.45, match=0.6, anchor_set_version=ANCHORS.version,
            crop_jpeg=b"jpeg",
        ),
        e.OperatorAnswer: e.OperatorAnswer(id="q1", source="cam", score=1.0, stamp=3.0, operator="ada"),
        e.AnswerReply: e.AnswerReply(id="q1", source="cam", score=0.0, pairs=4),
        e.ExclusionRequest: e.ExclusionRequest(robot="r7", actor="alice", reason="invented outcomes"),
        e.StoreContents: e.StoreContents(
            backend="sqlite", location="/state/gcdtrav.store.sqlite3", pairs=3, bytes=180, max_pairs=50_000,
            max_bytes=16_000_000, sources=[e.KeptSource(source="r1", pairs=3, bytes=180, oldest=1.0, newest=2.0)],
            graded={"v1@0.3": 3},
        ),
        e.ExclusionList: e.ExclusionList(
            words=[e.ExclusionWord(robot="r7", excluded=True, at=1.0, actor="alice", reason="", instance="i1")]
        ),
        e.PlannedPath: e.PlannedPath(stamp=2.0, frame_id="odom", points=[(0.0, 0.0), (1.5, -0.5)]),
        e.OutcomeBatch: e.OutcomeBatch(
            outcomes=[e.TraversalOutcome(stamp=1.0, x=1.0, y=-2.0, score=0.8, kind="velocity", radius_m=0.3)],
            sent_at=2.0,
            dropped=1,
        ),
    }
)  # fmt: skip


def every_message_type() -> set[type[m.Message]]:
    found, todo = set(), [m.Message]
    while todo:
        for sub in todo.pop().__subclasses__():
            found.add(sub)
            todo.append(sub)
    return found


def fields_of(message: m.Message) -> dict[str, Any]:
    return msgpack.unpackb(message.pack(), raw=False)


def with_unknown_fields(model: BaseModel) -> dict[str, Any]:
    """The message's fields, every model in it (nested ones too) with a field no reader knows; anchor sets
    excepted: configuration, strict."""
    if isinstance(model, AnchorSet):
        return model.model_dump(mode="python")
    fields = {name: _with_unknown_fields(getattr(model, name)) for name in type(model).model_fields}
    return {**fields, "added_in_1_9": [1, "x"]}


def _with_unknown_fields(value: Any) -> Any:
    if isinstance(value, BaseModel):
        return with_unknown_fields(value)
    if isinstance(value, (list, tuple)):
        return [_with_unknown_fields(item) for item in value]
    if isinstance(value, dict):
        return {key: _with_unknown_fields(item) for key, item in value.items()}
    return value.value if isinstance(value, Enum) else value


def test_every_message_type_has_a_sample() -> None:
    assert every_message_type() == set(SAMPLES), "add a sample of the new message type above"


@pytest.mark.parametrize("kind", list(SAMPLES), ids=lambda kind: kind.__name__)
def test_a_message_with_fields_it_does_not_know_decodes_without_them(kind: type[m.Message]) -> None:
    sample = SAMPLES[kind]
    data = with_unknown_fields(sample)
    decoded = kind.unpack(msgpack.packb(data, use_bin_type=True))
    assert decoded == sample  # the unknown fields are dropped, not kept
    assert "added_in_1_9" not in decoded.model_dump()


@pytest.mark.parametrize("kind", list(SAMPLES), ids=lambda kind: kind.__name__)
def test_a_newer_minor_is_read_and_another_major_refused(kind: type[m.Message]) -> None:
    data = fields_of(SAMPLES[kind])
    assert data["schema_version"] == m.SCHEMA_VERSION
    major = m.schema_major(m.SCHEMA_VERSION)
    newer_minor = kind.unpack(msgpack.packb({**data, "schema_version": f"{major}.99"}))
    assert newer_minor.schema_version == f"{major}.99"
    with pytest.raises(m.SchemaVersionError, match=rf"schema version {major + 1}\.0, this reader reads {major}\.x"):
        kind.unpack(msgpack.packb({**data, "schema_version": f"{major + 1}.0"}))


def test_a_1_0_writer_without_a_version_or_with_an_integer_is_read() -> None:
    data = fields_of(SAMPLES[m.ErrorReply])
    del data["schema_version"]
    assert m.ErrorReply.unpack(msgpack.packb(data)).error == "x"
    assert m.ErrorReply.unpack(msgpack.packb({**data, "schema_version": 1})).schema_version == "1"


@pytest.mark.parametrize("version", ["", "one", "1.2.3", None, True, 1.5])
def test_a_malformed_version_is_a_clear_error(version: object) -> None:
    data = {**fields_of(SAMPLES[m.ErrorReply]), "schema_version": version}
    with pytest.raises(m.MessageError, match=r"is not 'major\.minor'"):
        m.ErrorReply.unpack(msgpack.packb(data))


def test_configuration_stays_strict() -> None:
    with pytest.raises(ValidationError, match="Extra inputs are not permitted"):
        ServiceSettings.model_validate({"histroy": 8})
    with pytest.raises(AnchorSetError, match="colour: unknown field"):
        AnchorSet.from_text(b'{"name": "x", "colour": "red", "anchors": [{"concept": "grass", "position": 0.5}]}')


def test_the_status_reports_the_service_schema_version() -> None:
    assert fields_of(SAMPLES[m.ServiceStatus])["schema_version"] == m.SCHEMA_VERSION


def test_decode_reads_msgpack_or_json_and_refuses_what_is_over_its_limit_unread() -> None:
    """One decode for every message a person or script may send as JSON: the same fields either way, the size
    limit before anything is read (MessageTooLarge, a MessageError), a clear error for anything else."""
    twist = e.Twist2D(vx=0.5, wz=0.1)
    as_json = b"  " + twist.model_dump_json().encode()  # leading whitespace: still JSON
    assert e.Twist2D.decode(twist.pack()) == twist == e.Twist2D.decode(as_json)
    assert e.Twist2D.decode(as_json, max_bytes=len(as_json)) == twist  # the limit is inclusive
    for payload in (as_json, twist.pack()):
        with pytest.raises(m.MessageTooLarge, match=f"Twist2D of {len(payload)} bytes exceeds the limit"):
            e.Twist2D.decode(payload, max_bytes=len(payload) - 1)
    with pytest.raises(m.MessageTooLarge):
        e.Twist2D.unpack(twist.pack(), max_bytes=1)
    for bad, message in ((b"{not json", "not a JSON Twist2D"), (b"[1, 2]", "msgpack"), (b'{"vy": 1}', "vx")):
        with pytest.raises(m.MessageError, match=message) as err:
            e.Twist2D.decode(bad)
        assert not isinstance(err.value, m.MessageTooLarge)


def test_an_outcome_a_newer_relay_sends_costs_only_itself_not_its_batch() -> None:
    """A newer relay may add an outcome kind (a Literal here); before, the whole batch of up to 1,000 was refused
    at an older service. The batch's other outcomes are taken, the others counted."""
    good = e.TraversalOutcome(stamp=1.0, x=0.0, y=0.0, score=0.5, kind="velocity").model_dump(mode="python")
    newer = {**good, "kind": "slip", "slip_ratio": 0.4}  # a kind and a field this reader does not know
    out_of_range = {**good, "score": 2.0}
    payload = msgpack.packb(
        {"outcomes": [good, newer, out_of_range, "not a map", good], "sent_at": 3.0, "dropped": 2}, use_bin_type=True
    )
    with pytest.raises(m.MessageError):
        e.OutcomeBatch.decode(payload)  # the whole batch, as a plain decode reads it
    batch, left_out = e.OutcomeBatch.decode_each(payload)
    assert len(batch.outcomes) == 2 and left_out == 3 and batch.dropped == 2 and batch.sent_at == 3.0
    for bad_batch in (b"\x93\x01\x02\x03", msgpack.packb({"outcomes": [good] * 1001, "sent_at": 1.0})):
        with pytest.raises(m.MessageError):  # not a batch, or more than a batch holds: the batch's own error
            e.OutcomeBatch.decode_each(bad_batch)
    with pytest.raises(m.MessageTooLarge):
        e.OutcomeBatch.decode_each(payload, max_bytes=10)
