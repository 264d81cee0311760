"""Planar-motion homography: the poses a single plane (a wall) allows, and the choice between them
(docs/theory.md section 3.4).

Facing a single wall (all inliers on one plane) the planar essential matrix is not unique: the
points allow two poses, and the refinement of :mod:`topomap.servo.relpose` (step 3, free depth per point) slides between them
and toward the rotation/sideways-translation confusion. The plane's homography ties the depths
together: under planar motion and a vertical plane it is
    H = R_y(theta) + t nᵀ / d,   t = (t_X, 0, t_Z), n = (n_X, 0, n_Z),
so m_cur ∝ H m_goal with H = [[h11, 0, h13], [0, 1, 0], [h31, 0, h33]] exactly: 4 unknowns,
2 equations per match, a 2-point minimal solver. Its decomposition has (at most) two solutions;
the true one keeps the same normal n for every current position, the other one's normal moves
with the camera (:func:`choose_plane_solution`, given the normals other views of the goal allow).
"""

from __future__ import annotations

import math

import numpy as np

from topomap.config import RelativePoseConfig
from topomap.motion import wrap_angle
from topomap.servo.lm import robust_lm
from topomap.servo.pose import PlaneSolution, RelativePose

__all__ = [
    "planar_homography_rows",
    "ransac_planar_homography",
    "decompose_planar_homography",
    "plane_solutions",
    "choose_plane_solution",
    "wall_normals",
]

_EPS = 1e-12  # guards the decomposition's division by |H| terms


def planar_homography_rows(goal_n: np.ndarray, cur_n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two (N, 5) blocks of linear equations in ``h = (h11, h13, h31, h33, h22)``, one per image axis.

    ``x_cur (h31 x_g + h33) = h11 x_g + h13`` and ``y_cur (h31 x_g + h33) = h22 y_g``.
    """
    xg, yg, xc, yc = goal_n[:, 0], goal_n[:, 1], cur_n[:, 0], cur_n[:, 1]
    z, o = np.zeros_like(xg), np.ones_like(xg)
    return np.stack([xg, o, -xc * xg, -xc, z], 1), np.stack([z, z, yc * xg, yc, -yg], 1)


def _homography_sq(h: np.ndarray, goal_n: np.ndarray, cur_n: np.ndarray) -> np.ndarray:
    """(B, 5) homographies (h22 = 1) x N matches -> (B, N) squared transfer errors in the current image."""
    xg, yg = goal_n[None, :, 0], goal_n[None, :, 1]
    w = h[:, 2:3] * xg + h[:, 3:4]
    w = np.where(np.abs(w) < 1e-9, 1e-9, w)
    rx = (h[:, 0:1] * xg + h[:, 1:2]) / w - cur_n[None, :, 0]
    ry = h[:, 4:5] * yg / w - cur_n[None, :, 1]
    return rx * rx + ry * ry


def ransac_planar_homography(goal_n: np.ndarray, cur_n: np.ndarray, threshold: float, *, iters: int = 96,
                             seed: int = 0, min_abs_y: float = 0.02,
                             min_inlier_fraction: float = 0.0) -> tuple[np.ndarray, np.ndarray] | None:
    """MSAC over the 2-point planar-motion homography, then a robust least-squares refinement.

    ``goal_n, cur_n``: (N, 2) normalised coordinates; ``threshold``: inlier transfer distance
    (normalised). Returns ``(h (5,) with h22 = 1, inlier_mask (N,) bool)`` or None (fewer than 2
    usable matches, or MSAC's inliers below ``min_inlier_fraction`` — then the refinement is
    skipped). Deterministic for a given ``seed``.
    """
    n = len(goal_n)
    usable = np.flatnonzero(np.abs(goal_n[:, 1]) >= min_abs_y)  # y fixes the scale row of H
    if n < 2 or len(usable) < 2:
        return None
    rng = np.random.default_rng(seed)
    r1, r2 = planar_homography_rows(goal_n, cur_n)
    pick = np.stack([rng.choice(usable, 2, replace=False) for _ in range(iters)])
    _, _, vt = np.linalg.svd(np.concatenate([r1[pick], r2[pick]], axis=1), full_matrices=True)
    h = vt[:, -1, :]
    h = h[np.abs(h[:, 4]) > 1e-9]
    if not len(h):
        return None
    h = h / h[:, 4:5]
    e2 = _homography_sq(h, goal_n, cur_n)
    t2 = threshold * threshold
    best = h[int(np.argmin(np.minimum(e2, t2).sum(axis=1)))]
    inl = _homography_sq(best[None], goal_n, cur_n)[0] < t2
    if inl.sum() < max(2.0, min_inlier_fraction * n):
        return None
    g, c = goal_n[inl], cur_n[inl]

    def residuals(p):
        w = p[2] * g[:, 0] + p[3]
        w = np.where(np.abs(w) < 1e-9, 1e-9, w)
        return np.concatenate([(p[0] * g[:, 0] + p[1]) / w - c[:, 0], g[:, 1] / w - c[:, 1]])

    h = np.append(robust_lm(residuals, best[:4], threshold, iters=20).x, 1.0)
    return h, _homography_sq(h[None], goal_n, cur_n)[0] < t2


def decompose_planar_homography(h: np.ndarray, goal_n: np.ndarray) -> list[PlaneSolution]:
    """The poses ``H = R_y(theta) + t nᵀ / d`` allows (h as from :func:`ransac_planar_homography`).

    ``det(H_xz - R(theta)) = 0`` gives ``cos(theta - alpha) = (1 + det H_xz) / r``: two headings;
    for each, ``H_xz - R(theta)`` is the rank-1 ``t nᵀ / d`` (SVD); ``n`` points so that the
    ``goal_n`` points lie in front. Scale: positions over the median depth ``Z_i = d / (n · m_i)``.
    """
    A, B, C, D = (float(v) for v in h[:4])
    r = math.hypot(A + D, B - C)
    if r < _EPS:
        return []
    alpha = math.atan2(B - C, A + D)
    delta = math.acos(max(-1.0, min(1.0, (1.0 + A * D - B * C) / r)))
    m = np.column_stack([goal_n[:, 0], np.ones(len(goal_n))])
    out = []
    for theta in ((alpha,) if delta < 1e-9 else (alpha + delta, alpha - delta)):
        c, s = math.cos(theta), math.sin(theta)
        u, sv, vt = np.linalg.svd(np.array([[A - c, B - s], [C + s, D - c]]))
        t, nrm = u[:, 0] * sv[0], vt[0]
        nm = m @ nrm
        if np.median(nm) < 0:
            t, nrm, nm = -t, -nrm, -nm
        c_over_d = -np.array([[c, -s], [s, c]]) @ t  # c = -R^T t (XZ block)
        depth = float(np.median(1.0 / np.maximum(nm, 1e-6)))  # median depth over d
        cx, cz = c_over_d / depth
        out.append(PlaneSolution(float(wrap_angle(theta)), float(cz), float(-cx), math.atan2(nrm[0], nrm[1]),
                                 float(sv[0]), float(np.mean(nm > 0))))
    return out



def plane_solutions(g: np.ndarray, c: np.ndarray, thr: float, cfg: RelativePoseConfig) -> list[PlaneSolution]:
    """All solutions of the inliers' planar homography, or [] if the inliers are not one plane
    (``thr``: transfer error bound, normalised — the bound the inliers met in the refinement)."""
    if cfg.plane_inlier_fraction >= 1.0:
        return []
    # a plane holds >= 90 % of the inliers or is of no interest: 24 pairs all miss it with p < 1e-17
    fit = ransac_planar_homography(g, c, thr, iters=24, seed=cfg.seed, min_abs_y=cfg.min_abs_y,
                                   min_inlier_fraction=0.9 * cfg.plane_inlier_fraction)
    if fit is None or fit[1].sum() < cfg.plane_inlier_fraction * len(g):
        return []
    h, inl = fit
    return decompose_planar_homography(h, g[inl])


def choose_plane_solution(pose: RelativePose, wall_normals, tol_deg: float = 6.0) -> RelativePose:
    """``pose`` with the one of its :attr:`~RelativePose.plane_solutions` whose wall normal agrees
    with ``wall_normals`` (angles [rad], e.g. from other views of the same goal image), when exactly
    one of them does; otherwise ``pose`` unchanged.

    The wall's normal in the goal camera is a property of the goal image: every view of the goal's
    wall from elsewhere allows the true normal plus a false one that depends on where that view was
    taken. A normal shared with another viewpoint is the wall's (if both agree, the two viewpoints
    lie in the same direction from the goal and nothing is decided).
    """
    sols = pose.plane_solutions
    if len(sols) < 2 or not len(wall_normals):
        return pose
    known = np.asarray(wall_normals, dtype=float)
    tol = math.radians(tol_deg)
    agree = [bool(np.any(np.abs(wrap_angle(known - p.normal)) < tol)) for p in sols]
    if agree[1] and not agree[0]:
        return pose.with_plane_solution(sols[1])
    return pose


def wall_normals(pose: RelativePose, min_t_over_d: float = 0.05) -> tuple[float, ...]:
    """The wall normals (angles [rad]) a planar pose allows, where its translation resolves them."""
    return tuple(p.normal for p in pose.plane_solutions if p.t_over_d >= min_t_over_d)

