"""Facing a single wall (topomap.servo.homography, docs/theory.md section 3): the planar-motion
homography's poses and the choice between them."""

from __future__ import annotations

import math

import numpy as np
from servo_synth import CAMERA, in_world, matches, median_goal_depth, relative, to_camera

from topomap.config import RelativePoseConfig
from topomap.motion import wrap_angle
from topomap.servo.homography import choose_plane_solution, decompose_planar_homography, ransac_planar_homography, wall_normals
from topomap.servo.pose import PoseStatus
from topomap.servo.relpose import relative_pose


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
    from topomap.servo.pose import PlaneSolution, RelativePose

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
