"""Message and configuration shapes shared by the gcdtrav service and its clients (no torch)."""

from gcdtrav.schemas.anchors import Anchor, AnchorSet, AnchorSetError, default_anchor_set
from gcdtrav.schemas.config import EngineSettings, Method

__all__ = ["Anchor", "AnchorSet", "AnchorSetError", "EngineSettings", "Method", "default_anchor_set"]
