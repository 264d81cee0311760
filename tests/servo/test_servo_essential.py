"""The planar essential matrix (topomap.servo.essential) on synthetic 3D points projected into two
camera poses (docs/theory.md section 3): entries, decomposition, minimal solver, MSAC."""

from __future__ import annotations

import math

import numpy as np
import pytest
from servo_synth import normalized_pair

from topomap.motion import wrap_angle
from topomap.servo.essential import (
    decompose_planar_essential,
    essential_design_matrix,
    planar_essential,
    ransac_iterations,
    ransac_planar_essential,
    solve_planar_essential_3pt,
)


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
