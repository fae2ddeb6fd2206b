"""Messages on the bus. Every payload is msgpack of one of these models (see docs/messages.md).

Service and client both import this package, so a field changes in exactly one place. One module per topic:
``base`` (the schema version, errors, packing), ``images`` (frames in), ``maps`` (maps out), ``credits`` (the
link to a robot's relay: credits and the relay's health), ``queries`` (questions and replies), ``grid`` (poses
in, the ground grid out), ``status`` (the status block). Import from the package: ``from
gcdtrav.schemas.messages import MapsMessage``.
"""

from gcdtrav.schemas.messages.base import (
    MSGPACK_ENCODING,
    SCHEMA_VERSION,
    M,
    Message,
    MessageError,
    MessageTooLarge,
    SchemaVersionError,
    check_schema_version,
    check_size,
    peek_fields,
    schema_major,
)
from gcdtrav.schemas.messages.credits import CREDIT_REASONS, CreditGrant, RelayHealth
from gcdtrav.schemas.messages.grid import GridHeader, GridMessage, Pose2D
from gcdtrav.schemas.messages.images import RAW_CHANNELS, ImageEnvelope, PixelEncoding
from gcdtrav.schemas.messages.maps import CompactMapsMessage, MapsHeader, MapsMessage
from gcdtrav.schemas.messages.queries import (
    AnchorHistoryEntry,
    AnchorHistoryReply,
    AnchorPoint,
    AnchorSetRejection,
    AnchorSetReply,
    ContextDistribution,
    ErrorReply,
    PathReply,
)
from gcdtrav.schemas.messages.status import (
    CameraPlacement,
    ExperienceStatus,
    GridCameraStatus,
    GridStatus,
    QuestionStatus,
    ServiceStatus,
    SourceStatus,
    SourceView,
)

__all__ = [
    "CREDIT_REASONS",
    "MSGPACK_ENCODING",
    "RAW_CHANNELS",
    "SCHEMA_VERSION",
    "AnchorHistoryEntry",
    "AnchorHistoryReply",
    "AnchorPoint",
    "AnchorSetRejection",
    "AnchorSetReply",
    "CameraPlacement",
    "CompactMapsMessage",
    "ContextDistribution",
    "CreditGrant",
    "ErrorReply",
    "ExperienceStatus",
    "GridCameraStatus",
    "GridHeader",
    "GridMessage",
    "GridStatus",
    "ImageEnvelope",
    "M",
    "MapsHeader",
    "MapsMessage",
    "Message",
    "MessageError",
    "MessageTooLarge",
    "PathReply",
    "PixelEncoding",
    "Pose2D",
    "QuestionStatus",
    "RelayHealth",
    "SchemaVersionError",
    "ServiceStatus",
    "SourceStatus",
    "SourceView",
    "check_schema_version",
    "check_size",
    "peek_fields",
    "schema_major",
]
