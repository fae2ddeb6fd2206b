"""What one processed frame publishes, without a bus: maps, preview, full-resolution maps."""

from __future__ import annotations

import pytest
from fakes import MAP_SIDE, processed
from gcdtrav.schemas.images import decode_image, decode_map_png16
from gcdtrav.schemas.messages import MapsMessage
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.runtime.outputs import OutputBuilder, preview_size


def build(frame=None, **settings: object):  # type: ignore[no-untyped-def]
    builder = OutputBuilder(ServiceSettings(instance="box-1", **settings), "fake")
    return {output.key: output for output in builder.build(frame or processed())}


def test_maps_carry_t_u_and_a_header_that_says_where_they_come_from() -> None:
    frame = processed()
    outputs = build(frame)
    maps = MapsMessage.unpack(outputs["gcdtrav/out/r1/front/maps"].payload)
    assert maps.header.source == "r1/front" and maps.header.instance == "box-1" and maps.header.seq == 0
    assert maps.header.image_size == (64, 48) and maps.header.map_shape == (MAP_SIDE, MAP_SIDE)
    assert maps.header.scale == (64 / MAP_SIDE, 48 / MAP_SIDE) and maps.header.stamp == 12.5
    t = decode_map_png16(maps.traversability_png)
    assert abs(t - frame.result.maps.traversability).max() <= 1 / 65535
    assert maps.traversability_full_png is None


def test_full_resolution_maps_are_at_the_image_size() -> None:
    maps = MapsMessage.unpack(build(full_resolution=True)["gcdtrav/out/r1/front/maps"].payload)
    assert maps.traversability_full_png is not None and maps.uncertainty_full_png is not None
    assert decode_map_png16(maps.uncertainty_full_png).shape == (48, 64)


@pytest.mark.parametrize(
    ("height", "width", "max_width"), [(48, 64, 640), (48, 640, 64), (600, 40, 640), (30, 2000, 64)]
)
def test_the_preview_is_t_over_the_image_beside_u_within_its_width(height: int, width: int, max_width: int) -> None:
    outputs = build(processed(height=height, width=width), preview_max_width=max_width)
    preview = decode_image(outputs["gcdtrav/out/r1/front/preview"].payload)
    half = preview_size(width, height, max_width)
    assert preview.shape[:2] == (half[1], 2 * half[0])
    assert preview.shape[1] <= max(max_width, 2)  # never upscaled, never wider than asked
    assert abs(half[1] / half[0] - height / width) <= 1 / half[0] + 1 / half[1]  # the aspect kept


def test_no_preview_when_switched_off() -> None:
    assert set(build(preview=False)) == {"gcdtrav/out/r1/front/maps"}
