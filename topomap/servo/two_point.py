"""Dynamic appearance servoing with 2 points (docs/theory.md section 3.5): :func:`two_point_candidates`
solves the static problem with 2 matches (at most two solutions), :class:`TwoPointTracker` keeps the
solution whose motion agrees with the commanded input over time. Not used by the servo (which has many matches per image); kept as the theory's
reference implementation, exercised by the tests."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from topomap.errors import points_array
from topomap.motion import Command, wrap_angle
from topomap.servo.pose import PoseStatus, RelativePose

__all__ = ["two_point_candidates", "TwoPointTracker"]

_EPS = 1e-12  # guards divisions by norms


def two_point_candidates(goal_n: np.ndarray, cur_n: np.ndarray, min_abs_y: float = 0.02) -> list[tuple[float, float, float]]:
    """All planar poses ``(theta, x_s, z_s)`` that 2 matches allow (docs/theory.md section 3).

    Each point's vertical coordinate gives its depth ratio ``s_i = y_goal / y_cur`` (constant camera
    height), so for a heading ``theta`` the point yields ``q_i = c / Z_goal,i`` in closed form; both
    ``q_i`` must be parallel: ``K + P cos(theta) + Q sin(theta) = 0`` — at most two roots. Roots that
    put a point behind the goal camera are dropped. Scale: ``lambda`` = harmonic mean of the two
    goal depths (``|c| / lambda = (a_1 + a_2) / 2``). Returns 0, 1 or 2 candidates.
    """
    goal_n = points_array(goal_n, "goal_n")
    cur_n = points_array(cur_n, "cur_n", rows=len(goal_n))
    goal_n, cur_n = goal_n[:2], cur_n[:2]
    if len(goal_n) < 2:
        return []
    yg, yc = goal_n[:, 1], cur_n[:, 1]
    if np.any(np.abs(yg) < min_abs_y) or np.any(np.abs(yc) < min_abs_y) or np.any(yg * yc <= 0):
        return []
    s = yg / yc
    A = np.column_stack([goal_n[:, 0], np.ones(2)])  # (X, Z) of m_goal
    nv = np.column_stack([cur_n[:, 0], np.ones(2)])  # (X, Z) of m_cur

    def cross(u, v):
        return u[0] * v[1] - u[1] * v[0]

    K = cross(A[0], A[1]) + s[0] * s[1] * cross(nv[0], nv[1])
    P = -s[1] * cross(A[0], nv[1]) + s[0] * cross(A[1], nv[0])
    Q = -s[1] * float(A[0] @ nv[1]) + s[0] * float(A[1] @ nv[0])
    M = math.hypot(P, Q)
    if M < _EPS or abs(K) > M:
        return []
    base, off = math.atan2(Q, P), math.acos(max(-1.0, min(1.0, -K / M)))
    roots = [base + off] if off < 1e-9 else [base + off, base - off]
    out = []
    for th in roots:
        c_, s_ = math.cos(th), math.sin(th)
        q = A - s[:, None] * np.column_stack([c_ * nv[:, 0] - s_ * nv[:, 1], s_ * nv[:, 0] + c_ * nv[:, 1]])
        if float(q[0] @ q[1]) < 0:
            continue  # one point behind the goal camera
        u = q[0] + q[1]
        nrm = np.linalg.norm(u)
        u = u / nrm if nrm > _EPS else np.array([0.0, 1.0])
        k = float(np.mean(q @ u))  # mean a_i
        out.append((float(wrap_angle(th)), k * u[1], -k * u[0]))
    return out


@dataclass
class _Track:
    theta: float
    xz: np.ndarray
    cost: float = 0.0
    evidence: float = 0.0


class TwoPointTracker:
    """Dynamic 2-point mode (docs/theory.md section 3, "Dynamic AS: 2 points suffice").

    With 2 matches the static problem has up to two solutions (:func:`two_point_candidates`). The
    tracker follows each solution over time (one-to-one association on the heading predicted with the
    commanded turn rate) and scores it by how well its motion agrees with the commanded input: the
    scaled displacement must point along ``G(theta) u`` (for a unicycle, along the heading). Neither
    the scale nor a forward disturbance enters that test. Once one track's cost is lower by
    ``decide_margin`` the pose is ``OK``; until then ``AMBIGUOUS`` (with the best guess).
    """

    def __init__(self, decide_margin: float = 9.0, direction_noise_deg: float = 5.0, min_abs_y: float = 0.02,
                 min_step_s: float = 1e-3):
        self.decide_margin = decide_margin  # cost gap (sum of squared normalised angles) that settles it
        self.direction_noise = math.radians(direction_noise_deg)  # expected error of a step's direction
        self.min_abs_y = min_abs_y
        self.min_step_s = min_step_s  # displacements shorter than this [lambda] carry no direction
        self.tracks: list[_Track] = []

    def reset(self) -> None:
        self.tracks = []

    def _advance(self, tr: _Track, cand, u: np.ndarray | None) -> _Track:
        th, x, z = cand
        xz = np.array([x, z])
        step = xz - tr.xz
        dist = float(np.linalg.norm(step))
        cost, evidence = tr.cost, tr.evidence
        if u is not None and dist > self.min_step_s and np.linalg.norm(u) > 0:
            mid = tr.theta + 0.5 * wrap_angle(th - tr.theta)
            cm, sm = math.cos(mid), math.sin(mid)
            expect = np.array([cm * u[0] - sm * u[1], sm * u[0] + cm * u[1]])
            ang = math.atan2(expect[0] * step[1] - expect[1] * step[0], float(expect @ step))
            cost += min(ang * ang, (math.pi / 4) ** 2) / self.direction_noise**2
            evidence += 1.0
        return _Track(th, xz, cost, evidence)

    def update(self, goal_n: np.ndarray, cur_n: np.ndarray, last_command: Command | None = None, dt: float = 0.1) -> RelativePose:
        """One frame: 2 matches (goal, current, normalised (2, 2)); ``last_command`` applied for ``dt`` [s] since the previous one."""
        goal_n = points_array(goal_n, "goal_n")
        cur_n = points_array(cur_n, "cur_n", rows=len(goal_n))
        if len(goal_n) < 2:
            return RelativePose(PoseStatus.TOO_FEW_POINTS, n_matches=len(goal_n), inlier_mask=np.zeros(len(goal_n), bool))
        cands = two_point_candidates(goal_n, cur_n, self.min_abs_y)
        base = dict(n_matches=len(goal_n), inliers=2, inlier_mask=np.ones(len(goal_n), bool))
        if not cands:
            self.tracks = []
            return RelativePose(PoseStatus.DEGENERATE, **{**base, "inliers": 0})
        if not self.tracks:
            self.tracks = [_Track(th, np.array([x, z])) for th, x, z in cands]
        else:
            u = None if last_command is None else np.array([last_command.v_f, last_command.v_h])
            turn = 0.0 if last_command is None else last_command.omega * dt
            pred = [tr.theta + turn for tr in self.tracks]

            def gap(i, cand):
                return abs(wrap_angle(cand[0] - pred[i]))

            if len(self.tracks) == 2 and len(cands) == 2:
                straight = gap(0, cands[0]) + gap(1, cands[1])
                crossed = gap(0, cands[1]) + gap(1, cands[0])
                order = [0, 1] if straight <= crossed else [1, 0]
                new = [self._advance(self.tracks[i], cands[order[i]], u) for i in range(2)]
            else:
                new = [self._advance(tr, min(cands, key=lambda cd, i=i: gap(i, cd)), u) for i, tr in enumerate(self.tracks)]
            uniq: list[_Track] = []  # tracks that collapsed onto one candidate: keep the cheaper
            for tr in sorted(new, key=lambda t: t.cost):
                if all(abs(wrap_angle(tr.theta - o.theta)) > 1e-9 or np.any(tr.xz != o.xz) for o in uniq):
                    uniq.append(tr)
            self.tracks = uniq
        best = min(self.tracks, key=lambda t: t.cost)
        others = [t for t in self.tracks if t is not best]
        settled = not others or min(t.cost for t in others) - best.cost > self.decide_margin
        status = PoseStatus.OK if settled else PoseStatus.AMBIGUOUS
        return RelativePose(status, theta=best.theta, x_s=float(best.xz[0]), z_s=float(best.xz[1]), **base)

