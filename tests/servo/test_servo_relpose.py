"""Relative pose from two images (topomap.servo.relpose) on synthetic 3D points projected into two
camera poses (docs/theory.md section 3): accuracy, scale conventions, pure rotation, degeneracies, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
from servo_synth import CAM_HEIGHT, CAMERA, GOAL, POINTS, in_world, matches, median_goal_depth, relative

from topomap.config import RelativePoseConfig
from topomap.errors import ConfigError, ShapeError
from topomap.motion import wrap_angle
from topomap.servo.pose import PoseStatus, scale_convention
from topomap.servo.relpose import relative_pose, relative_pose_normalized


# ---------------------------------------------------------------------------- relative pose
REL_POSES = [(-1.5, 0.4, 0.3), (-0.6, -0.5, -0.4), (0.6, 0.3, 0.2), (-2.5, 1.0, -0.5), (-0.3, 0.0, 0.05)]


@pytest.mark.parametrize("rel", REL_POSES)
def test_relative_pose_recovers_heading_direction_and_scaled_distance(rel):
    rng = np.random.default_rng(3)
    cur = in_world(rel)
    cp, gp, idx = matches(POINTS, cur, GOAL, rng, noise_px=0.5, outliers=0.2, max_points=250)
    rp = relative_pose(cp, gp, CAMERA)
    assert rp.status is PoseStatus.OK
    true = relative(cur, GOAL)
    lam = median_goal_depth(POINTS, GOAL, idx[idx >= 0])  # the median-depth convention
    assert abs(math.degrees(wrap_angle(rp.theta - true[2]))) < 0.5
    assert abs(math.degrees(wrap_angle(rp.phi - math.atan2(true[1], true[0])))) < 3.0
    assert rp.rho_s == pytest.approx(math.hypot(true[0], true[1]) / lam, rel=0.08)
    # polar coordinates of eq. 1.9
    assert rp.beta == pytest.approx(wrap_angle(rp.phi - rp.theta + math.pi))
    # outliers are rejected, true matches kept
    assert np.mean(idx[rp.inlier_mask] >= 0) > 0.98
    assert rp.inliers > 0.8 * np.sum(idx >= 0)
    assert rp.residual_px < 1.5


def test_camera_height_scale_is_metric_up_to_the_camera_height():
    rng = np.random.default_rng(4)
    cfg = RelativePoseConfig(scale="camera_height")
    for rel in [(-1.5, 0.4, 0.3), (-0.6, -0.5, -0.4), (-2.0, 0.0, 0.0)]:
        cur = in_world(rel)
        cp, gp, _ = matches(POINTS, cur, GOAL, rng, noise_px=0.5, outliers=0.1, max_points=300)
        rp = relative_pose(cp, gp, CAMERA, cfg)
        assert rp.status is PoseStatus.OK and rp.scale.value == "camera_height"
        assert rp.rho_s * CAM_HEIGHT == pytest.approx(math.hypot(rel[0], rel[1]), rel=0.1)


def test_accuracy_over_random_poses():
    # a statistical check over many scenes: median errors stay tight
    rng = np.random.default_rng(5)
    th_err, dist_err = [], []
    for _ in range(25):
        rel = (rng.uniform(-2.0, 0.5), rng.uniform(-1.0, 1.0), rng.uniform(-0.5, 0.5))
        cur = in_world(rel)
        cp, gp, idx = matches(POINTS, cur, GOAL, rng, noise_px=0.5, outliers=0.25, max_points=200)
        rp = relative_pose(cp, gp, CAMERA)
        if rp.status is not PoseStatus.OK:
            assert math.hypot(rel[0], rel[1]) < 0.05  # only a tiny translation may be unobservable
            continue
        lam = median_goal_depth(POINTS, GOAL, idx[idx >= 0])
        th_err.append(abs(math.degrees(wrap_angle(rp.theta - rel[2]))))
        dist_err.append(abs(rp.rho_s * lam - math.hypot(rel[0], rel[1])))
    assert len(th_err) >= 23
    assert np.median(th_err) < 0.25 and np.max(th_err) < 2.0
    assert np.median(dist_err) < 0.05


def test_pure_rotation_reports_theta_only():
    rng = np.random.default_rng(6)
    for theta in (0.0, 0.2, -0.45):
        cur = in_world((0.0, 0.0, theta))
        cp, gp, idx = matches(POINTS, cur, GOAL, rng, noise_px=0.5, outliers=0.2)
        rp = relative_pose(cp, gp, CAMERA)
        assert rp.status is PoseStatus.PURE_ROTATION
        assert rp.has_heading and not rp.has_translation
        assert abs(math.degrees(rp.theta - theta)) < 0.1
        assert math.isnan(rp.x_s) and math.isnan(rp.z_s)
        assert rp.f_ratio < RelativePoseConfig().rotation_f_ratio


def test_small_translation_is_still_observed():
    rng = np.random.default_rng(7)
    cur = in_world((-0.1, 0.05, 0.1))
    cp, gp, _ = matches(POINTS, cur, GOAL, rng, noise_px=0.5, outliers=0.1)
    rp = relative_pose(cp, gp, CAMERA)
    assert rp.status is PoseStatus.OK and rp.f_ratio > 5


def test_too_few_points_and_too_few_inliers():
    rng = np.random.default_rng(8)
    cp, gp, _ = matches(POINTS, in_world((-1.0, 0.2, 0.1)), GOAL, rng, noise_px=0.5)
    assert relative_pose(cp[:2], gp[:2], CAMERA).status is PoseStatus.TOO_FEW_POINTS
    assert relative_pose(np.zeros((0, 2)), np.zeros((0, 2)), CAMERA).status is PoseStatus.TOO_FEW_POINTS
    # random "matches": no planar motion explains them
    junk = rng.uniform([0, 0], [319, 239], (150, 2))
    rp = relative_pose(junk, rng.uniform([0, 0], [319, 239], (150, 2)), CAMERA)
    assert rp.status is PoseStatus.TOO_FEW_INLIERS and not rp.has_heading
    assert math.isnan(rp.theta)


def test_points_on_the_horizon_are_degenerate():
    # every point at camera height: y = 0 in both images, the epipolar constraint is 0 = 0
    rng = np.random.default_rng(9)
    flat = POINTS.copy()
    flat[:, 2] = CAM_HEIGHT
    cp, gp, _ = matches(flat, in_world((-1.0, 0.2, 0.1)), GOAL, rng, noise_px=0.0)
    rp = relative_pose(cp, gp, CAMERA)
    assert rp.status is PoseStatus.DEGENERATE


def test_bad_input_is_a_clear_error():
    with pytest.raises(ShapeError, match="row by row"):
        relative_pose(np.zeros((5, 2)), np.zeros((4, 2)), CAMERA)
    with pytest.raises(ShapeError, match=r"\(N, 2\).*\(40, 3\)"):  # not silently 60 matches
        relative_pose(np.zeros((40, 3)), np.zeros((40, 3)), CAMERA)
    with pytest.raises(ShapeError, match="shape \\(80,\\)"):
        relative_pose_normalized(np.zeros(80), np.zeros(80), CAMERA.fx)
    with pytest.raises(ShapeError, match="dtype"):
        relative_pose(np.array([["a", "b"]]), np.zeros((1, 2)), CAMERA)
    assert relative_pose([], [], CAMERA).status is PoseStatus.TOO_FEW_POINTS  # no matches at all
    with pytest.raises(ConfigError, match="choose one of: camera_height, median_depth"):
        RelativePoseConfig(scale="metric")
    with pytest.raises(ConfigError, match="choose one of"):
        scale_convention("nope")
    with pytest.raises(ConfigError):
        RelativePoseConfig(min_inliers=2)


def test_deterministic_and_nan_tolerant():
    rng = np.random.default_rng(10)
    cp, gp, _ = matches(POINTS, in_world((-1.0, 0.3, 0.2)), GOAL, rng, noise_px=0.5, outliers=0.2)
    a, b = relative_pose(cp, gp, CAMERA), relative_pose(cp, gp, CAMERA)
    assert (a.theta, a.x_s, a.z_s) == (b.theta, b.x_s, b.z_s)
    assert np.array_equal(a.inlier_mask, b.inlier_mask)
    cp2 = cp.copy()
    cp2[0] = np.nan
    c = relative_pose(cp2, gp, CAMERA)
    assert c.status is PoseStatus.OK and not c.inlier_mask[0] and len(c.inlier_mask) == len(cp)


def test_normalized_entry_point_matches_the_pixel_one():
    rng = np.random.default_rng(11)
    cp, gp, _ = matches(POINTS, in_world((-0.9, -0.2, -0.1)), GOAL, rng, noise_px=0.5)
    a = relative_pose(cp, gp, CAMERA)
    b = relative_pose_normalized(CAMERA.normalize(cp), CAMERA.normalize(gp), CAMERA.fx)
    assert a.theta == pytest.approx(b.theta) and a.x_s == pytest.approx(b.x_s)


@pytest.mark.parametrize("scale", ["median_depth", "camera_height"])
def test_scales_from_one_run_equal_three_runs(scale):
    """relative_pose_with_scales gives the very numbers of the three calls it replaces: the pose, the
    distance without the plane's choice, and the camera-height distance."""
    from dataclasses import replace

    from topomap.servo.relpose import relative_pose_with_scales

    cfg = RelativePoseConfig(scale=scale)
    rng = np.random.default_rng(3)
    for rel in [(-1.0, 0.3, 0.2), (-0.4, -0.2, -0.1), (0.0, 0.0, 0.3)]:
        cp, gp, _ = matches(POINTS, in_world(rel), GOAL, rng, noise_px=0.5, outliers=0.1)
        pose, rho, rho_floor = relative_pose_with_scales(cp, gp, CAMERA, cfg)
        ref = relative_pose(cp, gp, CAMERA, cfg)
        assert (pose.status, pose.theta) == (ref.status, ref.theta) or math.isnan(ref.theta)
        plain = relative_pose(cp, gp, CAMERA, replace(cfg, plane_inlier_fraction=1.0))
        floor = relative_pose(cp, gp, CAMERA, replace(cfg, scale="camera_height"))
        assert rho == (plain.rho_s if plain.status is PoseStatus.OK else None)
        assert rho_floor == (floor.rho_s if floor.status is PoseStatus.OK else None)
