"""Planar essential matrix: the 3-point minimal solver inside MSAC, its decomposition, and the
least-squares refinement of ``(theta, direction of c)`` with the per-point depths eliminated
(docs/theory.md section 3.2; conventions in :mod:`topomap.servo.pose`)."""

from __future__ import annotations

import math

import numpy as np

from topomap.servo.lm import LMFit, robust_lm

__all__ = [
    "planar_essential",
    "essential_design_matrix",
    "solve_planar_essential_3pt",
    "decompose_planar_essential",
    "ransac_iterations",
    "ransac_planar_essential",
]

_EPS = 1e-12  # guards divisions by squared norms


def rotation_y(theta: float) -> np.ndarray:
    """(3, 3) rotation by ``theta`` about the camera's vertical (Y) axis."""
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def planar_essential(theta: float, t_xz) -> np.ndarray:
    """``E = [t]_x R_y(theta)`` for ``t = (t_x, 0, t_z)`` (docs/theory.md section 3): 4 nonzero entries."""
    t_x, t_z = float(t_xz[0]), float(t_xz[-1])
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[0.0, -t_z, 0.0], [t_z * c + t_x * s, 0.0, t_z * s - t_x * c], [0.0, t_x, 0.0]])


def _e_from_theta_t(theta: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(B,) headings, (B, 2) translations (t_x, t_z) -> (B, 4) entries (e1, e2, e3, e4)."""
    c, s = np.cos(theta), np.sin(theta)
    tx, tz = t[:, 0], t[:, 1]
    return np.stack([-tz, tz * c + tx * s, tz * s - tx * c, tx], axis=1)


def essential_matrix(e: np.ndarray) -> np.ndarray:
    """(4,) entries ``(e1, e2, e3, e4)`` -> the (3, 3) planar essential matrix."""
    return np.array([[0.0, e[0], 0.0], [e[1], 0.0, e[2]], [0.0, e[3], 0.0]])


def essential_design_matrix(goal_n: np.ndarray, cur_n: np.ndarray) -> np.ndarray:
    """(N, 4): row i is linear in ``(e1, e2, e3, e4)``; ``m_curᵀ E m_goal = A e`` (docs/theory.md section 3)."""
    xg, yg = goal_n[:, 0], goal_n[:, 1]
    xc, yc = cur_n[:, 0], cur_n[:, 1]
    return np.stack([xc * yg, yc * xg, yc, yg], axis=1)


def solve_planar_essential_3pt(A3: np.ndarray) -> np.ndarray:
    """Minimal solver: (B, 3, 4) design rows of 3 matches -> (B, 4) unit null vectors ``e``."""
    _, _, vt = np.linalg.svd(A3, full_matrices=True)
    return vt[:, -1, :]


def decompose_planar_essential(e: np.ndarray):
    """(B, 4) entries -> ``theta`` (B,) and unit ``t = (t_x, t_z)`` (B, 2), ``t`` up to sign.

    docs/theory.md section 3: ``t ∝ (e4, -e1)`` and ``(e2, e3) = -R2(theta) (e1, e4)``; with noise both
    halves give ``t``, averaged after rotating back.
    """
    e = np.atleast_2d(e)
    a0, a1 = -e[:, 0], -e[:, 3]  # -(e1, e4)
    b0, b1 = e[:, 1], e[:, 2]  # (e2, e3) = R2(theta) a
    theta = np.arctan2(a0 * b1 - a1 * b0, a0 * b0 + a1 * b1)
    c, s = np.cos(theta), np.sin(theta)
    # R2(theta)^T b, an estimate of a
    ra0, ra1 = c * b0 + s * b1, -s * b0 + c * b1
    a0m, a1m = 0.5 * (a0 + ra0), 0.5 * (a1 + ra1)  # -(e1, e4)
    t = np.stack([-a1m, a0m], axis=1)  # t_x = e4 = -a1, t_z = -e1 = a0
    n = np.linalg.norm(t, axis=1, keepdims=True)
    return theta, t / np.maximum(n, _EPS)


def _reproj_sq_batch(theta: np.ndarray, t: np.ndarray, goal_n: np.ndarray, cur_n: np.ndarray) -> np.ndarray:
    """(B,) headings, (B, 2) translations x N matches -> (B, N) squared reprojection errors.

    The current camera sees point i along ``R m_goal,i - a_i R c_hat`` and ``R c_hat = -t``; the depth
    parameter ``a_i`` is eliminated in closed form, so each match tests both image coordinates
    (the vertical one carries the depth ratio, docs/theory.md section 3), not only the epipolar line.
    """
    c, s = np.cos(theta)[:, None], np.sin(theta)[:, None]
    xg, yg = goal_n[None, :, 0], goal_n[None, :, 1]
    x, y = cur_n[None, :, 0], cur_n[None, :, 1]
    gx, gz = c * xg + s, -s * xg + c  # R_y(theta) (xg, yg, 1)
    dx, dz = -t[:, 0:1], -t[:, 1:2]
    A1, b1 = dx - x * dz, gx - x * gz
    A2, b2 = -y * dz, yg - y * gz
    a = (A1 * b1 + A2 * b2) / np.maximum(A1 * A1 + A2 * A2, _EPS)
    pz = gz - a * dz
    pz = np.where(np.abs(pz) < 1e-9, 1e-9, pz)
    rx = (gx - a * dx) / pz - x
    ry = yg / pz - y
    return rx * rx + ry * ry


def ransac_iterations(inlier_fraction: float, sample_size: int, confidence: float, max_iters: int) -> int:
    """Hypotheses needed to draw one all-inlier sample with ``confidence`` (Fischler & Bolles),
    capped at ``max_iters``; no inliers yet (or too few for float precision) -> ``max_iters``."""
    if inlier_fraction >= 1.0:
        return 0
    p_good = inlier_fraction**sample_size
    miss = math.log1p(-p_good) if p_good > 0.0 else 0.0
    if miss == 0.0:
        return max_iters
    return int(min(max_iters, math.ceil(math.log(1.0 - confidence) / miss)))


def ransac_planar_essential(
    goal_n: np.ndarray,
    cur_n: np.ndarray,
    threshold: float,
    *,
    confidence: float = 0.999,
    max_iters: int = 500,
    min_iters: int = 128,
    seed: int = 0,
    batch: int = 64,
):
    """MSAC over the 3-point planar-essential solver.

    ``goal_n, cur_n``: (N, 2) float64 normalised coordinates; ``threshold``: inlier reprojection
    distance (normalised units). Hypotheses come from the linear 3-point solver on the epipolar
    constraint; they are scored by the reprojection error in both image coordinates
    (:func:`_reproj_sq_batch`), which rejects the wrong-heading solutions that a planar E with its
    one-dimensional test often lets through in a narrow field of view. Returns
    ``(e (4,), theta, t (2,), inlier_mask (N,) bool)``, or ``None`` for fewer than 3 matches.
    Deterministic for a given ``seed``.
    """
    n = len(goal_n)
    if n < 3:
        return None
    A = essential_design_matrix(goal_n, cur_n)
    rng = np.random.default_rng(seed)
    thr2 = threshold**2
    best_cost, best = math.inf, None
    needed, done = max_iters, 0
    while done < max(min_iters, min(needed, max_iters)) and done < max_iters:
        idx = rng.integers(0, n, size=(batch, 3))
        ok = (idx[:, 0] != idx[:, 1]) & (idx[:, 0] != idx[:, 2]) & (idx[:, 1] != idx[:, 2])
        idx = idx[ok]
        done += batch
        if len(idx) == 0:
            continue
        theta, t = decompose_planar_essential(solve_planar_essential_3pt(A[idx]))
        d2 = _reproj_sq_batch(theta, t, goal_n, cur_n)
        cost = np.minimum(d2 / thr2, 1.0).sum(axis=1)  # MSAC
        k = int(np.argmin(cost))
        if cost[k] < best_cost:
            best_cost, best = float(cost[k]), (theta[k], t[k])
            w = float((d2[k] < thr2).mean())
            needed = ransac_iterations(w, 3, confidence, max_iters)
    # local optimisation: linear refit of E on the inliers, kept if it scores better
    for _ in range(2):
        mask = _reproj_sq_batch(np.array([best[0]]), best[1][None], goal_n, cur_n)[0] < thr2
        if mask.sum() < 4:
            break
        _, _, vt = np.linalg.svd(A[mask], full_matrices=False)
        theta, t = decompose_planar_essential(vt[-1][None])
        cost = float(np.minimum(_reproj_sq_batch(theta, t, goal_n, cur_n)[0] / thr2, 1.0).sum())
        if cost >= best_cost:
            break
        best_cost, best = cost, (theta[0], t[0])
    theta, t = best
    mask = _reproj_sq_batch(np.array([theta]), t[None], goal_n, cur_n)[0] < thr2
    e = _e_from_theta_t(np.array([theta]), t[None])[0]
    return e, float(theta), t, mask



# ---------------------------------------------------------------------------- refinement
def per_point_depths(theta: float, psi: float, goal_n: np.ndarray, cur_n: np.ndarray):
    """Closed-form ``a_i = |c| / Z_goal,i`` for a heading and a direction of ``c``.

    Returns ``(a (N,), g (N, 3), d (3,))`` with ``g = R m_goal``, ``d = R c_hat``: the current camera
    sees point i along ``g_i - a_i d``. Algebraic least squares in both image coordinates.
    """
    R = rotation_y(theta)
    m_g = np.column_stack([goal_n, np.ones(len(goal_n))])
    g = m_g @ R.T
    d = R @ np.array([math.sin(psi), 0.0, math.cos(psi)])
    x, y = cur_n[:, 0], cur_n[:, 1]
    A1 = d[0] - x * d[2]
    b1 = g[:, 0] - x * g[:, 2]
    A2 = -y * d[2]
    b2 = g[:, 1] - y * g[:, 2]
    a = (A1 * b1 + A2 * b2) / np.maximum(A1 * A1 + A2 * A2, _EPS)
    return a, g, d


def reprojection_residuals(theta: float, psi: float, goal_n, cur_n, *, with_a: bool = True):
    """(2N,) reprojection residuals (x, y interleaved) for heading ``theta`` and direction ``psi`` of ``c``;
    ``with_a=False``: the rotation-only model (no translation, no per-point depth)."""
    if with_a:
        a, g, d = per_point_depths(theta, psi, goal_n, cur_n)
        P = g - a[:, None] * d[None, :]
    else:
        R = rotation_y(theta)
        P = np.column_stack([goal_n, np.ones(len(goal_n))]) @ R.T
    z = np.where(np.abs(P[:, 2]) < 1e-9, 1e-9, P[:, 2])
    return (P[:, :2] / z[:, None] - cur_n).ravel()


def rotation_only_heading(goal_n: np.ndarray, cur_n: np.ndarray) -> float:
    """Closed-form heading of the best rotation about Y between the two bearing sets (Wahba in the XZ plane)."""
    bg = np.column_stack([goal_n, np.ones(len(goal_n))])
    bc = np.column_stack([cur_n, np.ones(len(cur_n))])
    bg /= np.linalg.norm(bg, axis=1, keepdims=True)
    bc /= np.linalg.norm(bc, axis=1, keepdims=True)
    # bc ≈ R_y(theta) bg: in XZ, (X, Z)_c = [[c, s], [-s, c]] (X, Z)_g
    s = float(np.sum(bg[:, 2] * bc[:, 0] - bg[:, 0] * bc[:, 2]))
    c = float(np.sum(bg[:, 0] * bc[:, 0] + bg[:, 2] * bc[:, 2]))
    return math.atan2(s, c)


def depth_ratio_direction(theta: float, goal_n, cur_n, min_abs_y: float) -> float | None:
    """Direction of ``c`` from the per-point depth ratios ``y_goal / y_cur`` (docs/theory.md section 3)."""
    yg, yc = goal_n[:, 1], cur_n[:, 1]
    ok = (np.abs(yg) >= min_abs_y) & (np.abs(yc) >= min_abs_y) & (yg * yc > 0)
    if ok.sum() < 2:
        return None
    s = yg[ok] / yc[ok]
    Rt = rotation_y(theta).T
    m_c = np.column_stack([cur_n[ok], np.ones(ok.sum())]) @ Rt.T
    q = np.column_stack([goal_n[ok, 0] - s * m_c[:, 0], 1.0 - s * m_c[:, 2]])  # (q_X, q_Z) = c / Z_goal
    _, _, vt = np.linalg.svd(q, full_matrices=False)
    u = vt[0]
    if np.median(q @ u) < 0:
        u = -u
    return math.atan2(u[0], u[1])



def refine(goal_n, cur_n, theta0: float, psis: list[float], f_scale: float) -> LMFit:
    """Refine ``(theta, psi)`` robustly (Cauchy) so that a few surviving outliers do not pull."""
    best = None
    for psi0 in psis:
        res = robust_lm(lambda p: reprojection_residuals(p[0], p[1], goal_n, cur_n), [theta0, psi0], f_scale)
        if best is None or res.cost < best.cost:
            best = res
    return best

