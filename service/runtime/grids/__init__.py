"""Ground grids of the service: `state` (a grid, its cameras, fusion), `encoding` (an update's payloads),
`answers` (cell and path queries) and `outputs` (`GridOutputs`, the thread-safe front the worker and the
queryables use)."""

from gcdtrav.service.runtime.grids.answers import CELL_FORMS, MAX_PATH_POINTS
from gcdtrav.service.runtime.grids.encoding import GRID_MAP_BASIC_LAYERS, FusedGrid, GridUpdate, SpeedUpdate
from gcdtrav.service.runtime.grids.outputs import GridInput, GridOutputs
from gcdtrav.service.runtime.grids.state import CameraState, SourceGrid

__all__ = [
    "CELL_FORMS",
    "GRID_MAP_BASIC_LAYERS",
    "MAX_PATH_POINTS",
    "CameraState",
    "FusedGrid",
    "GridInput",
    "GridOutputs",
    "GridUpdate",
    "SourceGrid",
    "SpeedUpdate",
]
