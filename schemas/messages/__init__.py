"""Messages on the bus. Every payload is msgpack of one of these models (see docs/messages.md).

Service and client both import this package, so a field changes in exactly one place. One module per topic:
``base`` (the schema version, errors, packing), ``images`` (frames in), ``maps`` (maps out), ``credits`` (the
link to a robot's relay), ``queries``, ``grid`` (poses in, the grid out), ``status``. Import every name from
the package, which imports them all (pyproject.toml lets this file's imports go unused).
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
from gcdtrav.schemas.messages.credits import CREDIT_REASONS, CameraParked, CreditGrant, RelayHealth
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
    StoreStatus,
)
