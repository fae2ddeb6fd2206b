"""Model backends: image -> (n, h, w) logits. Only this layer imports torch."""

from gcdtrav.service.backends.base import BackendDescription, ModelUnavailableError, SegmentationBackend

DEFAULT_MODEL = "CIDAS/clipseg-rd64-refined"


def default_model() -> str:
    """The checkpoint to load when none is given: $GCDTRAV_MODEL, else the hub id."""
    import os

    return os.environ.get("GCDTRAV_MODEL", DEFAULT_MODEL)


__all__ = ["DEFAULT_MODEL", "BackendDescription", "ModelUnavailableError", "SegmentationBackend", "default_model"]
