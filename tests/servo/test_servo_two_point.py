"""The dynamic 2-point mode (topomap.servo.two_point, docs/theory.md section 3)."""

from __future__ import annotations

import math

import numpy as np
from servo_synth import GOAL, POINTS, normalized_pair, relative, to_camera

from topomap.motion import Command
from topomap.servo.pose import PoseStatus
from topomap.servo.two_point import TwoPointTracker, two_point_candidates


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
