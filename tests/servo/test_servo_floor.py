"""The near floor, aligned (topomap.servo.floor) on rendered images of the default world: the pose it
measures, where the matched features cannot tell a sideways step from a turn, and when it declines."""

from __future__ import annotations

import math

import numpy as np
import pytest

from topomap.errors import ShapeError
from topomap.servo.floor import FloorAligner
from topomap.sim.geometry import Pose

GOAL = (13.0, 8.0, 0.0)  # on the default world's loop, looking along its first corridor
HEIGHT = 0.8  # the simulator's camera height [m]


@pytest.fixture(scope="module")
def scene():
    from topomap.sim.render import PyBulletRenderer
    from topomap.sim.simulator import CAMERA_HEIGHT_M, default_camera
    from topomap.sim.world import default_world

    assert CAMERA_HEIGHT_M == HEIGHT
    camera = default_camera()
    r = PyBulletRenderer(default_world(), camera)
    yield r, camera
    r.close()


def _at(forward: float, left: float, turn_deg: float) -> Pose:
    """The camera ``forward`` / ``left`` of GOAL [m] in GOAL's frame, turned ``turn_deg`` counter-clockwise."""
    x, z, th = GOAL
    return Pose(x + forward * math.cos(th) - left * math.sin(th), z + forward * math.sin(th) + left * math.cos(th),
                th + math.radians(turn_deg))


@pytest.mark.parametrize("forward, left, turn_deg", [(0.0, 0.3, 0.0), (0.0, -0.25, 2.0), (-0.3, 0.15, -3.0), (0.0, 0.0, 0.0)])
def test_alignment_measures_the_pose_beside_and_behind_the_goal(scene, forward, left, turn_deg):
    renderer, camera = scene
    aligner = FloorAligner(renderer.render(Pose(*GOAL)), camera)
    assert aligner.textured
    # the heading to start from as the servo would give it, 2 deg off
    a = aligner.align(renderer.render(_at(forward, left, turn_deg)), camera, math.radians(turn_deg + 2.0))
    assert a is not None and a.confident(0.9, 0.015), a
    assert a.x_h * HEIGHT == pytest.approx(forward, abs=0.04)
    assert a.z_h * HEIGHT == pytest.approx(left, abs=0.04)
    assert math.degrees(a.theta) == pytest.approx(turn_deg, abs=1.0)
    assert a.distance_h * HEIGHT == pytest.approx(math.hypot(forward, left), abs=0.05)


def test_tracking_from_last_periods_pose_finds_the_same_pose(scene):
    """Docking aligns every period: tracked from the previous alignment (a docking robot moved a few
    cm since), the small search ends where the full one does; started at a pose the floor does not
    support (0.5 m off), it finds no confident pose near it rather than a wrong one."""
    from dataclasses import replace

    renderer, camera = scene
    aligner = FloorAligner(renderer.render(Pose(*GOAL)), camera)
    image = renderer.render(_at(-0.1, 0.12, 1.0))
    full = aligner.align(image, camera, 0.0)
    assert full is not None and full.confident(0.9, 0.015)
    tracked = aligner.align(image, camera, 0.0, near=replace(full, x_h=full.x_h + 0.05, z_h=full.z_h - 0.05))
    assert tracked is not None and tracked.confident(0.9, 0.015)
    assert (tracked.x_h - full.x_h) * HEIGHT == pytest.approx(0.0, abs=0.01)
    assert (tracked.z_h - full.z_h) * HEIGHT == pytest.approx(0.0, abs=0.01)
    astray = aligner.align(image, camera, 0.0, near=replace(full, z_h=full.z_h + 0.5 / HEIGHT))
    assert astray is None or not astray.confident(0.9, 0.015) or abs(astray.z_h - full.z_h) * HEIGHT < 0.02


def test_a_plain_floor_is_not_aligned(scene):
    """Plain paint (here: a uniform image) has nothing to align: no alignment rather than a guess."""
    _, camera = scene
    plain = np.full((camera.height, camera.width, 3), 128, np.uint8)
    aligner = FloorAligner(plain, camera)
    assert not aligner.textured
    assert aligner.align(plain, camera) is None


def test_a_plain_current_floor_scores_no_agreement(scene):
    """A textured keyframe floor against a current image whose floor is plain (paint, a saturated
    patch): the correlation of a flat patch is rounding error over rounding error, and read millions
    on plain office floors (tuning world 256), a "confident" alignment anywhere. It scores nothing."""
    renderer, camera = scene
    aligner = FloorAligner(renderer.render(Pose(*GOAL)), camera)
    image = renderer.render(_at(0.0, 0.1, 0.0)).copy()
    image[camera.height // 2 + 10:] = 97  # the near floor painted over
    poses = np.array([[0.0, dx, dz] for dx in (-0.2, 0.0, 0.2) for dz in (-0.2, 0.0, 0.2)])
    from topomap.servo.floor import GRID_STEP_PX, _grey

    with np.errstate(all="raise"):  # no division by a zero variance either
        score, _ = aligner._ncc(poses, _grey(image), camera, GRID_STEP_PX)
    assert np.all(np.isfinite(score)) and np.all(score < 0.5)
    a = aligner.align(image, camera)
    assert a is None or (a.ncc <= 1.0 and not a.confident(0.8, 0.015))


def test_another_place_does_not_align_confidently(scene):
    """The floor of a keyframe 3 m back and turned away is not where the camera stands: whatever pose
    the search ends at, it is not a confident one that puts the robot at the goal."""
    renderer, camera = scene
    aligner = FloorAligner(renderer.render(Pose(*GOAL)), camera)
    a = aligner.align(renderer.render(_at(-3.0, 0.5, 40.0)), camera)
    assert a is None or not a.confident(0.9, 0.015) or a.distance_h * HEIGHT > 0.3


def test_bad_images_raise_shape_errors(scene):
    _, camera = scene
    with pytest.raises(ShapeError):
        FloorAligner(np.zeros((10, 10), np.float32), camera)
    aligner = FloorAligner(np.random.default_rng(0).integers(0, 255, (camera.height, camera.width), dtype=np.uint8), camera)
    with pytest.raises(ShapeError):
        aligner.align(np.zeros((camera.height + 1, camera.width), np.uint8), camera)
