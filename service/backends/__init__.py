"""Model backends: image -> (n, h, w) logits. Only this layer imports torch."""

from gcdtrav.service.backends.base import ModelUnavailableError, SegmentationBackend

DEFAULT_MODEL = "CIDAS/clipseg-rd64-refined"

__all__ = ["DEFAULT_MODEL", "ModelUnavailableError", "SegmentationBackend"]
