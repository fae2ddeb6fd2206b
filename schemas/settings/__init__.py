"""Service settings, one module per section (like Frigate's config/ package): `base` (the error, the
precision modes), `ros`, `grids`, `risk`, `share` (reuse and scheduling), `experience` (`experience:` and
`ask:`), `service` (`ServiceSettings`, the tree of every section) and `env` (the loader: YAML file <
``GCDTRAV_*`` environment variables < command-line flags). Import from here."""

from gcdtrav.schemas.settings.base import (
    ENV_PREFIX,
    KEY_CHUNK,
    PRECISIONS,
    Precision,
    SettingsError,
    default_instance_name,
)
from gcdtrav.schemas.settings.env import load_settings
from gcdtrav.schemas.settings.experience import AskSettings, ExperienceSettings
from gcdtrav.schemas.settings.grids import (
    SINGLE_CAMERA_FIELDS,
    CameraIntrinsics,
    CameraMountSettings,
    GridCamera,
    GridSettings,
    GridSpeedSettings,
    GridTfSettings,
    PoseBufferSettings,
)
from gcdtrav.schemas.settings.risk import RiskSettings
from gcdtrav.schemas.settings.ros import IMAGE_TYPES, RosInput, RosNode, RosOutput
from gcdtrav.schemas.settings.service import ServiceSettings
from gcdtrav.schemas.settings.share import ReuseSettings, ScheduleSettings
from gcdtrav.schemas.settings.store import StoreSettings

__all__ = [
    "ENV_PREFIX",
    "IMAGE_TYPES",
    "KEY_CHUNK",
    "PRECISIONS",
    "SINGLE_CAMERA_FIELDS",
    "AskSettings",
    "CameraIntrinsics",
    "CameraMountSettings",
    "ExperienceSettings",
    "GridCamera",
    "GridSettings",
    "GridSpeedSettings",
    "GridTfSettings",
    "PoseBufferSettings",
    "Precision",
    "ReuseSettings",
    "RiskSettings",
    "RosInput",
    "RosNode",
    "RosOutput",
    "ScheduleSettings",
    "ServiceSettings",
    "SettingsError",
    "StoreSettings",
    "default_instance_name",
    "load_settings",
]
