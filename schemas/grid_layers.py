"""The one table of a ground grid's layers: the service encodes them from it, the client decodes them with it
and the viewer draws them from it (torch-free: the client reads it).

A row names a layer once: its name (grid_map's layer name, the key of ``Grid.layers`` in the client, the
viewer's channel), its byte format and its colour scale in the viewer. The GridMessage carries each layer as
``{name}_png`` (schemas/messages/grid.py). A new layer: a row here, its optional field in ``GridMessage`` and its
values in ``service/grid/layers.py`` (``GridLayers``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from gcdtrav.schemas.images import (
    decode_age_png,
    decode_count_png,
    decode_map_png16,
    encode_age_png,
    encode_all,
    encode_count_png,
    encode_map_png16,
)
from gcdtrav.schemas.messages import GridMessage
from numpy.typing import NDArray

COUNT = "count"  # the layer that says which cells are known (count > 0)


@dataclass(frozen=True)
class LayerCodec:
    """A layer's byte format: ``encode`` (values, NaN unknown) and ``decode`` (bytes; ``unknown_nan``: the
    decoded values are set NaN where the count layer says the cell is unknown)."""

    encode: Callable[[NDArray[Any]], bytes]
    decode: Callable[[bytes], NDArray[Any]]
    unknown_nan: bool


def _encode_fraction(values: NDArray[Any]) -> bytes:
    return encode_map_png16(np.nan_to_num(values))  # unknown cells travel as 0; the count says they are unknown


FRACTION = LayerCodec(_encode_fraction, decode_map_png16, True)  # [0, 1] as a 16-bit PNG (value / 65535)
# [0, 1] where every cell has a value, unknown ones included (the speed layer's is configured)
FRACTION_EVERYWHERE = LayerCodec(_encode_fraction, decode_map_png16, False)
COUNTS = LayerCodec(encode_count_png, decode_count_png, False)  # 16-bit, saturating at 65535
AGES = LayerCodec(encode_age_png, decode_age_png, False)  # tenths of a second; NaN: never observed


@dataclass(frozen=True)
class GridLayer:
    name: str
    codec: LayerCodec
    scale: str | None  # the viewer's colour scale (client/view/pictures.py SCALES); None: not drawn

    @property
    def field(self) -> str:
        """Its GridMessage field."""
        return f"{self.name}_png"


# In grid_map's layer order (a GridMap's layers, service/ros/grid_map.py).
GRID_LAYERS: tuple[GridLayer, ...] = (
    GridLayer("traversability", FRACTION, "T"),
    GridLayer("uncertainty", FRACTION, "U"),
    GridLayer("cvar", FRACTION, "cvar"),  # CVaR of T at header.alpha
    GridLayer("p_below", FRACTION, "p_below"),  # P(T < header.tau)
    GridLayer("match", FRACTION, "match"),  # the fused match score
    GridLayer(COUNT, COUNTS, None),
    GridLayer("age", AGES, "age"),  # seconds from the last observation to header.stamp
    GridLayer("speed", FRACTION_EVERYWHERE, "speed"),  # fraction of maximum speed; only from grids with speed
)
OPTIONAL = frozenset({"speed"})  # layers a grid publishes only when configured (GridLayers holds None)


def encode_layers(values: Mapping[str, NDArray[Any]]) -> dict[str, bytes]:
    """{GridMessage field: bytes} of every layer in the table (``values`` by layer name; an optional layer may be
    absent), encoded concurrently."""
    present = [layer for layer in GRID_LAYERS if layer.name in values or layer.name not in OPTIONAL]
    encoded = encode_all([(layer.codec.encode, values[layer.name]) for layer in present])
    return {layer.field: data for layer, data in zip(present, encoded, strict=True)}


def decode_layers(message: GridMessage) -> dict[str, NDArray[Any]]:
    """The layers the message carries, by name (an older writer's lack the newer ones); NaN where unknown
    (age: where never observed). MessageError or ImageDecodeError if a layer is not its format."""
    count = decode_count_png(message.count_png)
    unknown = count == 0
    layers: dict[str, NDArray[Any]] = {}
    for layer in GRID_LAYERS:
        data = getattr(message, layer.field)
        if data is None:
            continue
        values = count if layer.name == COUNT else layer.codec.decode(data)
        if layer.codec.unknown_nan:
            values[unknown] = np.nan
        layers[layer.name] = values
    return layers
