"""The change measure: sensor noise and exposure flicker are no change, a person walking in is."""

from __future__ import annotations

import math

import numpy as np
import pytest
from gcdtrav.schemas.images import decode_image
from gcdtrav.schemas.messages import ImageEnvelope, PixelEncoding, Pose2D
from gcdtrav.schemas.settings.share import ReuseSettings
from gcdtrav.service.runtime.frames import PendingFrame
from gcdtrav.service.runtime.triage.change import glance, moved_fraction, pose_moved, pose_speeds, thumbnail_of_rgb
from scenes import flicker, jpeg_frame, noisy, scene, with_person

SETTINGS = ReuseSettings()
LIMITS = (20_000_000, 40_000_000)


def moved(a: np.ndarray, b: np.ndarray) -> float:
    """Moved fraction between two views as the service glances at them (JPEG, reduced grey decode)."""
    first = glance(jpeg_frame(a), *LIMITS, SETTINGS.blocks).thumbnail
    second = glance(jpeg_frame(b), *LIMITS, SETTINGS.blocks).thumbnail
    return moved_fraction(first, second, SETTINGS.block_threshold)


@pytest.mark.parametrize("sigma", [2.0, 6.0, 12.0])
def test_sensor_noise_moves_no_block(sigma: float) -> None:
    view = scene()
    assert moved(noisy(view, sigma, 1), noisy(view, sigma, 2)) <= SETTINGS.changed_fraction


@pytest.mark.parametrize(("gain", "offset"), [(1.3, 0.0), (0.7, 10.0), (1.0, 35.0), (1.15, -20.0)])
def test_exposure_and_gain_flicker_cancel(gain: float, offset: float) -> None:
    view = scene()
    assert moved(view, noisy(flicker(view, gain, offset), 4.0, 3)) <= SETTINGS.changed_fraction


def test_a_person_walking_in_is_a_change_also_under_flicker() -> None:
    view = scene()
    assert moved(view, with_person(view)) > SETTINGS.changed_fraction
    assert moved(view, flicker(with_person(noisy(view, 6.0, 4)), 1.2, 5.0)) > SETTINGS.changed_fraction


def test_a_pan_of_a_few_pixels_per_frame_adds_up_against_the_reference() -> None:
    """A creeping robot: each step small, but against the last inferred view the motion shows."""
    assert moved(scene(shift=0), scene(shift=40)) > SETTINGS.changed_fraction


def test_a_flat_dark_view_with_noise_is_not_divided_by_its_noise() -> None:
    dark = np.full((480, 640, 3), 8, np.uint8)
    assert moved(noisy(dark, 3.0, 5), noisy(dark, 3.0, 6)) <= SETTINGS.changed_fraction
    assert moved(noisy(dark, 3.0, 5), with_person(noisy(dark, 3.0, 6))) > SETTINGS.changed_fraction


def test_the_cheap_jpeg_path_and_the_decoded_image_give_the_same_thumbnail() -> None:
    """The reference of an inferred frame may come from its decoded image: it must compare as unchanged."""
    frame = jpeg_frame(scene())
    cheap = glance(frame, *LIMITS, SETTINGS.blocks).thumbnail
    full = thumbnail_of_rgb(decode_image(frame.payload), SETTINGS.blocks)
    assert cheap.shape == (SETTINGS.blocks[1], SETTINGS.blocks[0])
    assert moved_fraction(cheap, full, SETTINGS.block_threshold) == 0.0


def test_an_envelope_gives_its_stamp_and_frame_id_and_a_bare_image_its_receipt() -> None:
    view = scene()
    bare = jpeg_frame(view, received_at=100.0)
    assert glance(bare, *LIMITS, SETTINGS.blocks).stamp == 100.0
    envelope = ImageEnvelope(
        stamp=42.0,
        frame_id="cam",
        encoding=PixelEncoding.JPEG,
        width=640,
        height=480,
        data=bare.payload,
    )
    wrapped = PendingFrame("r1/front", "gcdtrav/in/r1/front", envelope.pack(), "application/msgpack", 100.0)
    seen = glance(wrapped, *LIMITS, SETTINGS.blocks)
    assert (seen.stamp, seen.frame_id) == (42.0, "cam")
    raw = ImageEnvelope(
        stamp=43.0, frame_id="c2", encoding=PixelEncoding.RGB8, width=640, height=480, data=view.tobytes()
    )
    seen_raw = glance(PendingFrame("r", "k", raw.pack(), "application/msgpack", 1.0), *LIMITS, SETTINGS.blocks)
    assert seen_raw.stamp == 43.0
    assert moved_fraction(seen.thumbnail, seen_raw.thumbnail, SETTINGS.block_threshold) <= SETTINGS.changed_fraction


def test_an_undecodable_frame_raises_for_the_worker_to_count() -> None:
    with pytest.raises(Exception):  # noqa: B017 - whichever the decoder raises; the worker counts it by reason
        glance(PendingFrame("r", "k", b"\xff\xd8 not really a jpeg", "image/jpeg", 1.0), *LIMITS, SETTINGS.blocks)


def pose(x: float = 0.0, y: float = 0.0, yaw_deg: float = 0.0, stamp: float = 0.0) -> Pose2D:
    return Pose2D(stamp=stamp, x=x, y=y, yaw=math.radians(yaw_deg))


def test_turning_in_place_is_a_pose_change_and_the_yaw_wraps() -> None:
    assert pose_moved(pose(), pose(yaw_deg=5), SETTINGS)
    assert not pose_moved(pose(), pose(yaw_deg=1), SETTINGS)
    assert not pose_moved(pose(yaw_deg=179.5), pose(yaw_deg=-179.5), SETTINGS)  # 1 degree across the wrap
    assert pose_moved(pose(), pose(x=0.1), SETTINGS) and not pose_moved(pose(), pose(y=0.01), SETTINGS)


def test_pose_speeds_need_ordered_stamps() -> None:
    speeds = pose_speeds(pose(stamp=1.0), pose(x=1.0, yaw_deg=10, stamp=3.0))
    assert speeds is not None and speeds[0] == pytest.approx(0.5) and speeds[1] == pytest.approx(5.0)
    assert pose_speeds(pose(stamp=2.0), pose(stamp=2.0)) is None
