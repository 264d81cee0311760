"""Relative pose from two images (topomap.servo.geometry), on synthetic 3D points projected into two
camera poses (docs/theory.md section 3): planar essential matrix, minimal solver, RANSAC, refinement, scale
conventions, degeneracies, and the 2-point dynamic mode."""

from __future__ import annotations

import math

import numpy as np
import pytest
from servo_synth import CAM_HEIGHT, CAMERA, matches, median_goal_depth, relative, room_points, to_camera

from topomap.config import RelativePoseConfig
from topomap.errors import ConfigError
from topomap.motion import Command
from topomap.servo.geometry import (
    PoseStatus,
    TwoPointTracker,
    decompose_planar_essential,
    decompose_planar_homography,
    essential_design_matrix,
    planar_essential,
    ransac_iterations,
    ransac_planar_essential,
    ransac_planar_homography,
    relative_pose,
    relative_pose_normalized,
    scale_convention,
    solve_planar_essential_3pt,
    choose_plane_solution,
    two_point_candidates,
    wall_normals,
    wrap_angle,
)

POINTS = room_points(np.random.default_rng(42))
GOAL = (0.4, -0.2, 0.3)


def in_world(rel, goal=GOAL):
    """A pose given in the goal frame (x forward, z left, theta) -> world."""
    c, s = math.cos(goal[2]), math.sin(goal[2])
    return (goal[0] + c * rel[0] - s * rel[1], goal[1] + s * rel[0] + c * rel[1], goal[2] + rel[2])


def normalized_pair(rel, rng, noise_px=0.0, **kw):
    cur = in_world(rel)
    cp, gp, idx = matches(POINTS, cur, GOAL, rng, noise_px=noise_px, **kw)
    return CAMERA.normalize(cp), CAMERA.normalize(gp), idx


# ---------------------------------------------------------------------------- planar E
def test_planar_essential_has_four_nonzero_entries_and_satisfies_the_epipolar_constraint():
    rng = np.random.default_rng(0)
    rel = (-0.8, 0.3, 0.25)
    cur_n, goal_n, _ = normalized_pair(rel, rng)
    # X_cur = R_y(theta)(X_goal - c); t = -R c; in the camera frame c = (-z, 0, x)
    theta = rel[2]
    c = np.array([-rel[1], 0.0, rel[0]])
    R = np.array([[math.cos(theta), 0, math.sin(theta)], [0, 1, 0], [-math.sin(theta), 0, math.cos(theta)]])
    t = -R @ c
    E = planar_essential(theta, (t[0], t[2]))
    assert np.count_nonzero(np.abs(E) > 1e-12) == 4
    assert E[0, 0] == E[0, 2] == E[1, 1] == E[2, 0] == E[2, 2] == 0
    mc = np.column_stack([cur_n, np.ones(len(cur_n))])
    mg = np.column_stack([goal_n, np.ones(len(goal_n))])
    assert np.max(np.abs(np.einsum("ij,jk,ik->i", mc, E, mg))) < 1e-12
    # the design matrix is the same constraint, linear in (e1, e2, e3, e4)
    e = np.array([E[0, 1], E[1, 0], E[1, 2], E[2, 1]])
    assert np.max(np.abs(essential_design_matrix(goal_n, cur_n) @ e)) < 1e-12


def test_decomposition_recovers_theta_and_translation_up_to_sign():
    rng = np.random.default_rng(1)
    for _ in range(100):
        theta = rng.uniform(-math.pi, math.pi)
        t = rng.normal(size=2)
        t /= np.linalg.norm(t)
        E = planar_essential(theta, t) * rng.choice([-1.0, 1.0]) * rng.uniform(0.1, 10)
        th, tt = decompose_planar_essential(np.array([[E[0, 1], E[1, 0], E[1, 2], E[2, 1]]]))
        assert wrap_angle(th[0] - theta) == pytest.approx(0.0, abs=1e-9)
        assert abs(abs(float(tt[0] @ t)) - 1.0) < 1e-9


def test_three_point_minimal_solver_is_exact_on_noise_free_points():
    rng = np.random.default_rng(2)
    rel = (-1.2, -0.4, -0.35)
    cur_n, goal_n, _ = normalized_pair(rel, rng)
    # three points well off the horizon and apart in the image (a well-conditioned sample)
    far = np.argsort(-np.abs(goal_n[:, 1]))[:40]
    pick = far[[np.argmin(goal_n[far, 0]), np.argmax(goal_n[far, 0]), np.argmin(np.abs(goal_n[far, 0]))]]
    A = essential_design_matrix(goal_n[pick], cur_n[pick])
    e = solve_planar_essential_3pt(A[None])
    th, _ = decompose_planar_essential(e)
    assert wrap_angle(th[0] - rel[2]) == pytest.approx(0.0, abs=1e-9)


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
    with pytest.raises(ConfigError, match="differ in length"):
        relative_pose(np.zeros((5, 2)), np.zeros((4, 2)), CAMERA)
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


# ---------------------------------------------------------------------------- 2 points
def test_two_points_give_at_most_two_solutions_one_of_them_true():
    rng = np.random.default_rng(12)
    found = 0
    for _ in range(60):
        rel = (rng.uniform(-2, 0), rng.uniform(-1, 1), rng.uniform(-0.4, 0.4))
        cur_n, goal_n, idx = normalized_pair(rel, rng)
        ok = (np.abs(cur_n[:, 1]) > 0.05) & (np.abs(goal_n[:, 1]) > 0.05)
        sel = rng.choice(np.flatnonzero(ok), 2, replace=False)
        cands = two_point_candidates(goal_n[sel], cur_n[sel])
        assert 1 <= len(cands) <= 2
        depth = to_camera(POINTS[idx[sel]], GOAL)[:, 2]
        lam = 1.0 / np.mean(1.0 / depth)  # |c| / lambda = mean of |c| / Z_i
        truth = (rel[2], rel[0] / lam, rel[1] / lam)
        found += any(np.allclose(c, truth, atol=1e-7) for c in cands)
    assert found == 60


def test_two_point_tracker_settles_on_the_true_solution_while_driving():
    # two features seen from a unicycle driving forward while turning: the static problem has two
    # solutions; the motion tells them apart (docs/theory.md section 3, dynamic AS)
    pts = np.array([[4.0, 1.0, 0.1], [5.0, -1.5, 2.2]])
    goal = (0.0, 0.0, 0.0)
    tracker = TwoPointTracker()
    pose, dt, cmd = (-1.5, -0.3, 0.25), 0.1, Command(0.3, 0.0, -0.1)
    statuses, errors = [], []
    for k in range(20):
        gl, cur = to_camera(pts, goal), to_camera(pts, pose)
        g, c = gl[:, :2] / gl[:, 2:], cur[:, :2] / cur[:, 2:]
        if k == 0:
            assert len(two_point_candidates(g, c)) == 2
        rp = tracker.update(g, c, cmd if k else None, dt)
        statuses.append(rp.status)
        errors.append(abs(rp.theta - relative(pose, goal)[2]))
        pose = (pose[0] + cmd.v_f * dt * math.cos(pose[2] + cmd.omega * dt / 2),
                pose[1] + cmd.v_f * dt * math.sin(pose[2] + cmd.omega * dt / 2), pose[2] + cmd.omega * dt)
    assert statuses[0] is PoseStatus.AMBIGUOUS
    settled = statuses.index(PoseStatus.OK)
    assert settled <= 5 and all(s is PoseStatus.OK for s in statuses[settled:])
    assert max(errors[settled:]) < 1e-9


# ---------------------------------------------------------------------------- a single wall
WALL = np.column_stack([np.random.default_rng(5).uniform(-4, 4, 900), np.full(900, 3.0),
                        np.random.default_rng(6).uniform(0.0, 2.5, 900)])  # the wall z = 3 (x, z, height)
WALL_GOAL = (0.3, 0.6, math.pi / 2 + 0.35)  # facing the wall obliquely
# an approach that ends beside the goal, turned: where the wall's two poses differ most
WALL_APPROACH = [(-0.8, 0.3, 0.1), (-0.7, 0.35, 0.05), (-0.6, 0.35, 0.0), (-0.5, 0.3, -0.05), (-0.4, 0.25, -0.08),
                 (-0.3, 0.25, -0.1), (-0.2, 0.25, -0.12), (-0.1, 0.25, -0.12), (0.0, 0.25, -0.1)]


def _wall_normal_in_goal() -> float:
    P = to_camera(WALL[:2], WALL_GOAL)
    d = P[1, [0, 2]] - P[0, [0, 2]]
    n = np.array([d[1], -d[0]])
    n = n if n @ P[0, [0, 2]] > 0 else -n
    return math.atan2(n[0], n[1])


def test_planar_homography_decomposition_contains_the_true_pose_and_wall_normal():
    rng = np.random.default_rng(0)
    rel = (-0.5, 0.3, -0.05)
    cur = in_world(rel, WALL_GOAL)
    cp, gp, idx = matches(WALL, cur, WALL_GOAL, rng, noise_px=0.0, max_points=200)
    g, c = CAMERA.normalize(gp), CAMERA.normalize(cp)
    h, inl = ransac_planar_homography(g, c, 1.0 / CAMERA.fx)
    assert inl.all()
    sols = decompose_planar_homography(h, g)
    assert len(sols) == 2
    true = relative(cur, WALL_GOAL)
    lam = median_goal_depth(WALL, WALL_GOAL, idx)
    best = min(sols, key=lambda p: abs(p.theta - true[2]))
    assert abs(best.theta - true[2]) < 1e-6
    assert np.allclose([best.x_s, best.z_s], np.array(true[:2]) / lam, atol=1e-6)
    assert abs(wrap_angle(best.normal - _wall_normal_in_goal())) < 1e-6
    other = sols[1] if best is sols[0] else sols[0]
    assert abs(wrap_angle(other.normal - best.normal)) > math.radians(5)  # the false one tilts the wall


def _wall_pose(rel, rng, **kw):
    cur = in_world(rel, WALL_GOAL)
    cp, gp, idx = matches(WALL, cur, WALL_GOAL, rng, noise_px=0.5, max_points=200, **kw)
    return relative_pose(cp, gp, CAMERA), relative(cur, WALL_GOAL), median_goal_depth(WALL, WALL_GOAL, idx[idx >= 0])


def test_facing_a_wall_the_essential_matrix_slips_and_a_second_viewpoint_fixes_it():
    rng = np.random.default_rng(5)
    # another view of the goal's wall, taken from behind the goal (as the previous node of a route)
    neighbour, _, _ = _wall_pose((-0.9, -0.05, 0.05), rng)
    known = wall_normals(neighbour)
    assert len(known) == 2  # the wall's normal and a false one
    assert min(abs(wrap_angle(np.array(known) - _wall_normal_in_goal()))) < math.radians(3)
    e_heading_err, chosen_err = [], []
    for rel in WALL_APPROACH:
        pose, true, lam = _wall_pose(rel, rng, outliers=0.1)
        assert pose.status is PoseStatus.OK and pose.plane_solutions
        assert min(abs(wrap_angle(p.normal - _wall_normal_in_goal())) for p in pose.plane_solutions) < math.radians(5)
        chosen = choose_plane_solution(pose, known)
        e_heading_err.append(abs(math.degrees(wrap_angle(pose.theta - true[2]))))
        chosen_err.append((abs(math.degrees(wrap_angle(chosen.theta - true[2]))),
                           math.hypot(chosen.x_s - true[0] / lam, chosen.z_s - true[1] / lam)))
    assert max(e_heading_err) > 2.5  # the ambiguity is real: alone, the essential matrix picks the wrong pose
    assert max(h for h, _ in chosen_err[3:]) < 1.0 and max(p for _, p in chosen_err[3:]) < 0.02


def test_choose_plane_solution_needs_exactly_one_agreeing_normal():
    from topomap.servo.geometry import PlaneSolution, RelativePose

    a = PlaneSolution(0.10, 0.2, 0.0, 0.5, 0.2, 1.0)
    b = PlaneSolution(-0.05, 0.2, 0.1, 0.2, 0.2, 1.0)
    pose = RelativePose(PoseStatus.OK, theta=a.theta, x_s=a.x_s, z_s=a.z_s, plane_solutions=(a, b))
    assert choose_plane_solution(pose, ()).theta == 0.10  # nothing known: the essential matrix's choice
    assert choose_plane_solution(pose, (0.21, -0.7)).theta == -0.05  # b's normal seen elsewhere
    assert choose_plane_solution(pose, (0.21, 0.49)).theta == 0.10  # both agree: undecided
    assert choose_plane_solution(pose, (1.5,)).theta == 0.10  # neither
    not_planar = RelativePose(PoseStatus.OK, theta=0.3, x_s=1.0, z_s=0.0)
    assert choose_plane_solution(not_planar, (0.3,)) is not_planar


def test_plane_solutions_can_be_switched_off():
    rng = np.random.default_rng(5)
    cur = in_world(WALL_APPROACH[5], WALL_GOAL)
    cp, gp, _ = matches(WALL, cur, WALL_GOAL, rng, noise_px=0.5, max_points=200)
    assert relative_pose(cp, gp, CAMERA).plane_solutions
    assert relative_pose(cp, gp, CAMERA, RelativePoseConfig(plane_inlier_fraction=1.0)).plane_solutions == ()


def test_ransac_iterations_never_divide_by_zero():
    assert ransac_iterations(1.0, 3, 0.999, 500) == 0
    assert ransac_iterations(0.5, 3, 0.999, 500) == 52  # log(0.001) / log(1 - 1/8)
    for w in (0.0, 1e-7, 1e-300):  # no inliers, or a sample probability below float resolution
        assert ransac_iterations(w, 3, 0.999, 500) == 500


def test_planar_essential_ransac_on_pure_outliers_returns_without_error():
    """Found by the navigation benchmark on a world textured with other photographs: a hypothesis
    with no inlier at all used to divide by log(1) = 0."""
    rng = np.random.default_rng(3)
    goal, cur = rng.uniform(-1, 1, (12, 2)), rng.uniform(-1, 1, (12, 2)) * 40.0
    ransac_planar_essential(goal, cur, 1e-4, seed=0)  # must not raise
