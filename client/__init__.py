"""gcdtrav client library: talk to the traversability service over Zenoh (no torch)."""

from gcdtrav.client.client import (
    ActivationLost,
    AnchorSetRejected,
    Grid,
    Maps,
    PartialSwap,
    QueryTimeout,
    ServiceError,
    TraversabilityClient,
)
from gcdtrav.client.session.zenoh_args import add_zenoh_arguments, zenoh_config, zenoh_config_from_args

__all__ = [
    "ActivationLost",
    "AnchorSetRejected",
    "Grid",
    "Maps",
    "PartialSwap",
    "QueryTimeout",
    "ServiceError",
    "TraversabilityClient",
    "add_zenoh_arguments",
    "zenoh_config",
    "zenoh_config_from_args",
]
