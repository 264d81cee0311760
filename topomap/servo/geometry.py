"""Scaled planar relative pose of the current camera w.r.t. a target camera, from matched points.

docs/theory.md section 3 (static and dynamic appearance servoing). The camera rides at a constant height
with a horizontal optical axis, so the current camera differs from the target (goal) camera by a
rotation ``theta`` about the vertical axis and a horizontal translation.

Frames and conventions
----------------------
* Camera axes are OpenCV's: X right, Y down, Z forward. ``m = (x, y, 1)`` are normalised image
  coordinates (``topomap.camera.CameraIntrinsics.normalize``).
* Goal camera -> current camera: ``X_cur = R (X_goal - c)`` with ``R = R_y(theta)`` and ``c`` the
  current camera centre in the goal camera frame (``c_Y = 0``); the essential matrix is
  ``E = [t]_x R`` with ``t = -R c`` and ``m_curᵀ E m_goal = 0``.
* The result is reported as a vehicle pose in the goal frame, docs/theory.md section 1: ``x`` forward,
  ``z`` to the left, ``theta`` counter-clockwise (``x = c_Z``, ``z = -c_X``); polar coordinates
  ``rho, phi = atan2(z, x), beta = phi - theta + pi`` (eq. 1.9). The camera is taken to sit on the
  vehicle's rotation axis.

Scale convention (the one unknown constant lambda of docs/theory.md section 3)
--------------------------------------------------------------------------
Positions are reported as ``(x, z) / lambda``:

* ``median_depth`` (default): ``lambda`` = median depth, in the goal camera, of the inlier points.
  It is a property of the goal image (for a given goal it only varies with which points match), needs
  no assumption about the scene, and works for any camera.
* ``camera_height``: ``lambda`` = the camera height above the floor. It uses the camera-height
  trick (docs/theory.md section 3: the vertical image coordinate carries depth because the camera
  height is constant): floor points are the lowest points below the horizon, so
  ``|c| / h = quantile(a_i / y_i)`` over points below the horizon. The result is metric once
  multiplied by the camera height, which is fixed and known to the robot; it needs a visible,
  textured floor.

Both follow from the per-point quantity ``a_i = |c| / Z_goal,i`` that the refinement estimates; both
go to zero continuously as the current camera reaches the goal, where the translation direction is
no longer observable but its smallness still is.

Pipeline of :func:`relative_pose`
---------------------------------
1. planar essential matrix, 4 nonzero entries, 3-point minimal solver (SVD null vector) inside
   MSAC — OpenCV has no planar-motion essential-matrix solver, hence the hand-written one. Each
   hypothesis is scored by the reprojection error in both image coordinates with the per-point
   depth eliminated in closed form (the vertical coordinate carries the depth ratio), which rejects
   wrong-heading models that the one-dimensional epipolar test accepts in a narrow field of view;
2. decomposition ``theta, t`` (docs/theory.md section 3) — the twisted pair is not planar, so only the
   sign of ``t`` is ambiguous;
3. least-squares refinement on the inliers of the reprojection error in both image coordinates
   over ``(theta, direction of c)``, the per-point ``a_i`` eliminated in closed form (variable
   projection); the sign of ``c`` by positive depth (cheirality: most ``a_i > 0``);
4. a (trimmed) F-test against the rotation-only model: if translation does not explain the images
   significantly better, the status is ``PURE_ROTATION`` and only ``theta`` is reported. With
   ~150 matches at 0.5 px noise in a room of ~5 m, translations above ~5 cm are detected.

Known limit: with few points (~60) and a mostly sideways motion, rotation and sideways translation
are nearly confounded (the bas-relief ambiguity of narrow fields of view); heading errors of ~1 deg
then remain.

The dynamic 2-point mode (docs/theory.md section 3, "Dynamic AS: 2 points suffice") is
:func:`two_point_candidates` (the static problem with 2 points: at most two solutions) plus
:class:`TwoPointTracker` (keeps the solution whose motion agrees with the commanded input over time).
"""

from __future__ import annotations

import enum
import logging
import math
from dataclasses import dataclass, field, replace

import numpy as np

from topomap.camera import CameraIntrinsics
from topomap.config import RelativePoseConfig
from topomap.errors import ConfigError, unknown_choice
from topomap.motion import Command, wrap_angle

__all__ = [
    "PoseStatus",
    "ScaleConvention",
    "RelativePose",
    "PlaneSolution",
    "choose_plane_solution",
    "wall_normals",
    "planar_homography_rows",
    "ransac_iterations",
    "ransac_planar_homography",
    "decompose_planar_homography",
    "scale_convention",
    "planar_essential",
    "essential_design_matrix",
    "solve_planar_essential_3pt",
    "decompose_planar_essential",
    "ransac_planar_essential",
    "relative_pose",
    "relative_pose_normalized",
    "two_point_candidates",
    "TwoPointTracker",
]

log = logging.getLogger(__name__)

_EPS = 1e-12


class PoseStatus(str, enum.Enum):
    """Outcome of a relative-pose reconstruction."""

    OK = "ok"  # heading and scaled position are valid
    PURE_ROTATION = "pure_rotation"  # heading valid; translation below what the images resolve
    AMBIGUOUS = "ambiguous"  # 2-point mode: two solutions still agree with the motion so far
    TOO_FEW_POINTS = "too_few_points"  # not enough matches were given
    TOO_FEW_INLIERS = "too_few_inliers"  # no planar-motion model gathers enough inliers
    DEGENERATE = "degenerate"  # the points cannot fix the geometry (all on the horizon, ...)

    @property
    def has_heading(self) -> bool:
        return self in (PoseStatus.OK, PoseStatus.PURE_ROTATION, PoseStatus.AMBIGUOUS)

    @property
    def has_translation(self) -> bool:
        return self in (PoseStatus.OK, PoseStatus.AMBIGUOUS)


class ScaleConvention(str, enum.Enum):
    """What the unknown scale lambda is (module docstring)."""

    MEDIAN_DEPTH = "median_depth"
    CAMERA_HEIGHT = "camera_height"


def scale_convention(name: str | ScaleConvention) -> ScaleConvention:
    """Parse a scale convention name; an unknown one lists the valid choices."""
    if isinstance(name, ScaleConvention):
        return name
    try:
        return ScaleConvention(str(name).lower())
    except ValueError:
        raise unknown_choice("scale convention", name, [s.value for s in ScaleConvention]) from None


@dataclass(frozen=True)
class PlaneSolution:
    """One pose a planar-motion homography allows (:func:`decompose_planar_homography`).

    ``theta, x_s, z_s`` as in :class:`RelativePose` (median-depth scale); ``normal``: direction of the
    plane's normal in the goal camera's XZ plane, ``atan2(n_X, n_Z)`` [rad] (0 = a wall facing the
    goal camera); ``t_over_d``: translation over the plane's distance (how well ``normal`` is
    determined: it is undefined at zero translation); ``visible``: fraction of the points in front
    of the plane's visible side.
    """

    theta: float
    x_s: float
    z_s: float
    normal: float
    t_over_d: float
    visible: float


@dataclass(frozen=True, eq=False)
class RelativePose:
    """Scaled planar pose of the current camera in the goal frame (docs/theory.md sections 1, 3).

    ``theta`` relative heading, counter-clockwise [rad] (NaN when unknown); ``x_s, z_s`` position
    forward / leftward of the goal, divided by the scale ``lambda`` of ``scale`` (NaN when the
    translation is not observable); ``inlier_mask``: (N,) bool over the given matches;
    ``residual_px``: RMS reprojection error of the inliers [px]; ``f_ratio``: how much better the
    translating model explains the inliers than a pure rotation (F statistic, ~1 = no evidence);
    ``essential``: (3, 3) float64 planar essential matrix (unit norm) or None;
    ``plane_solutions``: when the inliers lie on one plane (a wall), the poses its homography allows
    (one or two, see :func:`decompose_planar_homography`) — the reported pose is one of them, the one
    the essential matrix agrees with; a caller that knows the plane's normal may pick another.
    """

    status: PoseStatus
    theta: float = math.nan
    x_s: float = math.nan
    z_s: float = math.nan
    inliers: int = 0
    inlier_mask: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    n_matches: int = 0
    scale: ScaleConvention = ScaleConvention.MEDIAN_DEPTH
    residual_px: float = math.nan
    f_ratio: float = math.nan
    essential: np.ndarray | None = None
    plane_solutions: tuple[PlaneSolution, ...] = ()

    def with_plane_solution(self, sol: PlaneSolution) -> RelativePose:
        """This pose with the heading and position of another of its :attr:`plane_solutions`."""
        return replace(self, theta=sol.theta, x_s=sol.x_s, z_s=sol.z_s)

    @property
    def has_heading(self) -> bool:
        return self.status.has_heading

    @property
    def has_translation(self) -> bool:
        return self.status.has_translation

    @property
    def rho_s(self) -> float:
        """Scaled distance ``rho / lambda`` to the goal (eq. 1.9)."""
        return math.hypot(self.x_s, self.z_s)

    @property
    def phi(self) -> float:
        """``atan2(z, x)``: direction of the current position seen from the goal (eq. 1.9) [rad]."""
        return math.atan2(self.z_s, self.x_s)

    @property
    def beta(self) -> float:
        """``phi - theta + pi``: bearing of the goal seen from the vehicle (eq. 1.9) [rad]."""
        return wrap_angle(self.phi - self.theta + math.pi)

    @property
    def direction(self) -> np.ndarray:
        """(2,) unit vector ``(x, z) / rho`` (translation direction in the goal frame)."""
        r = self.rho_s
        return np.array([self.x_s / r, self.z_s / r]) if r > 0 else np.full(2, math.nan)

    @property
    def position_s(self) -> np.ndarray:
        """(2,) float64 ``(x_s, z_s)``."""
        return np.array([self.x_s, self.z_s])

    @property
    def xi_s(self) -> tuple[float, float, float]:
        """Scaled pose ``(x/lambda, z/lambda, theta)`` in the goal frame."""
        return (self.x_s, self.z_s, self.theta)


# ============================================================================ planar essential matrix
def _ry(theta: float) -> np.ndarray:
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


def _e_matrix(e: np.ndarray) -> np.ndarray:
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


# ============================================================================ planar homography
# Facing a single wall (all inliers on one plane) the planar essential matrix is not unique: the
# points allow two poses, and the refinement of step 3 (free depth per point) slides between them
# and toward the rotation/sideways-translation confusion. The plane's homography ties the depths
# together: under planar motion and a vertical plane it is
#     H = R_y(theta) + t nᵀ / d,   t = (t_X, 0, t_Z), n = (n_X, 0, n_Z),
# so m_cur ∝ H m_goal with H = [[h11, 0, h13], [0, 1, 0], [h31, 0, h33]] exactly: 4 unknowns,
# 2 equations per match, a 2-point minimal solver. Its decomposition has (at most) two solutions;
# the true one keeps the same normal n for every current position, the other one's normal moves
# with the camera (:func:`choose_plane_solution`, given the normals other views of the goal allow).


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

    h = np.append(_robust_lm(residuals, best[:4], threshold, iters=20).x, 1.0)
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


# ============================================================================ refinement
def _per_point_a(theta: float, psi: float, goal_n: np.ndarray, cur_n: np.ndarray):
    """Closed-form ``a_i = |c| / Z_goal,i`` for a heading and a direction of ``c``.

    Returns ``(a (N,), g (N, 3), d (3,))`` with ``g = R m_goal``, ``d = R c_hat``: the current camera
    sees point i along ``g_i - a_i d``. Algebraic least squares in both image coordinates.
    """
    R = _ry(theta)
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


def _reproj_residuals(theta: float, psi: float, goal_n, cur_n, *, with_a: bool = True):
    if with_a:
        a, g, d = _per_point_a(theta, psi, goal_n, cur_n)
        P = g - a[:, None] * d[None, :]
    else:
        R = _ry(theta)
        P = np.column_stack([goal_n, np.ones(len(goal_n))]) @ R.T
    z = np.where(np.abs(P[:, 2]) < 1e-9, 1e-9, P[:, 2])
    return (P[:, :2] / z[:, None] - cur_n).ravel()


def _rotation_only_theta(goal_n: np.ndarray, cur_n: np.ndarray) -> float:
    """Closed-form heading of the best rotation about Y between the two bearing sets (Wahba in the XZ plane)."""
    bg = np.column_stack([goal_n, np.ones(len(goal_n))])
    bc = np.column_stack([cur_n, np.ones(len(cur_n))])
    bg /= np.linalg.norm(bg, axis=1, keepdims=True)
    bc /= np.linalg.norm(bc, axis=1, keepdims=True)
    # bc ≈ R_y(theta) bg: in XZ, (X, Z)_c = [[c, s], [-s, c]] (X, Z)_g
    s = float(np.sum(bg[:, 2] * bc[:, 0] - bg[:, 0] * bc[:, 2]))
    c = float(np.sum(bg[:, 0] * bc[:, 0] + bg[:, 2] * bc[:, 2]))
    return math.atan2(s, c)


def _pca_direction(theta: float, goal_n, cur_n, min_abs_y: float) -> float | None:
    """Direction of ``c`` from the per-point depth ratios ``y_goal / y_cur`` (docs/theory.md section 3)."""
    yg, yc = goal_n[:, 1], cur_n[:, 1]
    ok = (np.abs(yg) >= min_abs_y) & (np.abs(yc) >= min_abs_y) & (yg * yc > 0)
    if ok.sum() < 2:
        return None
    s = yg[ok] / yc[ok]
    Rt = _ry(theta).T
    m_c = np.column_stack([cur_n[ok], np.ones(ok.sum())]) @ Rt.T
    q = np.column_stack([goal_n[ok, 0] - s * m_c[:, 0], 1.0 - s * m_c[:, 2]])  # (q_X, q_Z) = c / Z_goal
    _, _, vt = np.linalg.svd(q, full_matrices=False)
    u = vt[0]
    if np.median(q @ u) < 0:
        u = -u
    return math.atan2(u[0], u[1])


class _Fit:
    __slots__ = ("x", "fun", "cost")

    def __init__(self, x, fun, cost):
        self.x, self.fun, self.cost = x, fun, cost


def _robust_lm(fun, x0, f_scale: float, iters: int = 15) -> _Fit:
    """Levenberg-Marquardt with Cauchy IRLS weights for 1-2 parameters.

    Hand-written because scipy.optimize.least_squares spends ~3 ms per call in overhead at this size
    (measured), several times the work itself, and this runs at every control step.
    """
    x = np.asarray(x0, dtype=float).copy()
    f = fun(x)
    c2 = f_scale * f_scale

    def robust_cost(r):
        return float(np.sum(np.log1p(r * r / c2)))

    cost, mu, h = robust_cost(f), 1e-3, 1e-6
    for _ in range(iters):
        w = 1.0 / (1.0 + f * f / c2)  # Cauchy IRLS weights
        J = np.empty((len(f), len(x)))
        for j in range(len(x)):
            xj = x.copy()
            xj[j] += h
            J[:, j] = (fun(xj) - f) / h
        Jw = J * w[:, None]
        A, g = Jw.T @ J, Jw.T @ f
        improved = False
        for _ in range(8):
            try:
                dx = -np.linalg.solve(A + mu * np.diag(np.diag(A) + 1e-12), g)
            except np.linalg.LinAlgError:
                mu *= 10.0
                continue
            f_new = fun(x + dx)
            c_new = robust_cost(f_new)
            if c_new < cost:
                x, f, improved = x + dx, f_new, True
                mu = max(mu / 3.0, 1e-9)
                converged = cost - c_new < 1e-6 * cost or np.max(np.abs(dx)) < 1e-7
                cost = c_new
                break
            mu *= 10.0
        if not improved or converged:
            break
    return _Fit(x, f, cost)


def _fit(goal_n, cur_n, theta0: float, psis: list[float], f_scale: float) -> _Fit:
    """Refine ``(theta, psi)`` robustly (Cauchy) so that a few surviving outliers do not pull."""
    best = None
    for psi0 in psis:
        res = _robust_lm(lambda p: _reproj_residuals(p[0], p[1], goal_n, cur_n), [theta0, psi0], f_scale)
        if best is None or res.cost < best.cost:
            best = res
    return best


# ============================================================================ public entry points
def relative_pose(
    matched_cur_px: np.ndarray,
    matched_goal_px: np.ndarray,
    camera: CameraIntrinsics,
    config: RelativePoseConfig | None = None,
    goal_camera: CameraIntrinsics | None = None,
) -> RelativePose:
    """Scaled planar pose of the current camera w.r.t. the goal camera from matched pixels.

    ``matched_cur_px, matched_goal_px``: (N, 2) pixel coordinates, row i of one matching row i of the
    other; ``camera``: intrinsics of the current image (``goal_camera`` of the goal image, default
    the same). Never raises for bad geometry: the status says what went wrong.
    """
    cur = np.asarray(matched_cur_px, dtype=np.float64).reshape(-1, 2)
    goal = np.asarray(matched_goal_px, dtype=np.float64).reshape(-1, 2)
    if len(cur) != len(goal):
        raise ConfigError(f"matched point arrays differ in length ({len(cur)} vs {len(goal)}); pass matches row by row")
    goal_camera = goal_camera or camera
    f_px = 0.5 * (camera.fx + camera.fy)
    return relative_pose_normalized(camera.normalize(cur), goal_camera.normalize(goal), f_px, config)


def relative_pose_normalized(
    cur_n: np.ndarray, goal_n: np.ndarray, focal_px: float, config: RelativePoseConfig | None = None
) -> RelativePose:
    """:func:`relative_pose` on (N, 2) normalised coordinates; ``focal_px`` converts thresholds to pixels."""
    cfg = config or RelativePoseConfig()
    scale = scale_convention(cfg.scale)
    cur_n = np.asarray(cur_n, dtype=np.float64).reshape(-1, 2)
    goal_n = np.asarray(goal_n, dtype=np.float64).reshape(-1, 2)
    n = len(cur_n)
    finite = np.isfinite(cur_n).all(axis=1) & np.isfinite(goal_n).all(axis=1)
    mask = np.zeros(n, bool)
    base = dict(n_matches=n, scale=scale, inlier_mask=mask)
    if finite.sum() < max(3, cfg.min_inliers):
        return RelativePose(PoseStatus.TOO_FEW_POINTS, **base)
    idx_f = np.flatnonzero(finite)
    g_all, c_all = goal_n[idx_f], cur_n[idx_f]

    # 1-2. planar E by 3-point MSAC, decomposition
    thr = cfg.ransac_px / focal_px
    out = ransac_planar_essential(
        g_all, c_all, thr, confidence=cfg.ransac_confidence, max_iters=cfg.ransac_max_iters,
        min_iters=min(cfg.ransac_min_iters, cfg.ransac_max_iters), seed=cfg.seed,
    )
    e, theta0, t0, inl = out
    if inl.sum() < cfg.min_inliers:
        return RelativePose(PoseStatus.TOO_FEW_INLIERS, inliers=int(inl.sum()), **base)
    g, c = g_all[inl], c_all[inl]
    if np.count_nonzero(np.abs(g[:, 1]) > cfg.min_abs_y) < 3:
        # every row of the design matrix needs y != 0: points on the horizon fix nothing
        return RelativePose(PoseStatus.DEGENERATE, inliers=int(inl.sum()), **base)

    # 3. refinement: reprojection error over (theta, direction of c), a_i eliminated
    c_hat0 = -_ry(theta0).T @ np.array([t0[0], 0.0, t0[1]])
    psis = [math.atan2(c_hat0[0], c_hat0[2])]
    psi_pca = _pca_direction(theta0, g, c, cfg.min_abs_y)
    if psi_pca is not None:
        psis.append(psi_pca)
    fit = _fit(g, c, theta0, psis, thr)
    theta, psi = float(fit.x[0]), float(fit.x[1])
    # reject matches the full model cannot explain (epipolar-consistent but wrong in y), refit once
    r = fit.fun.reshape(-1, 2)
    good = np.hypot(r[:, 0], r[:, 1]) * focal_px < 2.0 * cfg.ransac_px
    if good.sum() < cfg.min_inliers:
        return RelativePose(PoseStatus.TOO_FEW_INLIERS, inliers=int(good.sum()), **base)
    if not good.all():
        inl[np.flatnonzero(inl)[~good]] = False
        g, c = g[good], c[good]
        fit = _fit(g, c, theta, [psi], thr)
        theta, psi = float(fit.x[0]), float(fit.x[1])
    mask[idx_f[inl]] = True
    n_in = int(inl.sum())
    r2_full = np.sum(fit.fun.reshape(-1, 2) ** 2, axis=1)

    # 4. translation significance against the rotation-only model on the same inliers. Per point,
    # the rotation model has one parameter less (the depth a_i); under a pure rotation
    # r2_rot - r2_full and r2_full have about the same distribution, so their means' ratio is ~1.
    # Trimmed means, because a few outliers lying along epipolar lines survive (a_i absorbs them).
    th_rot = _robust_lm(lambda p: _reproj_residuals(p[0], 0.0, g, c, with_a=False), [_rotation_only_theta(g, c)], thr).x[0]
    r2_rot = np.sum(_reproj_residuals(th_rot, 0.0, g, c, with_a=False).reshape(-1, 2) ** 2, axis=1)
    diff = r2_rot - r2_full
    keep = diff <= np.quantile(diff, 0.9)  # trimmed: the surviving outliers have the largest diff
    f_ratio = float(np.mean(diff[keep]) / max(float(np.mean(r2_full[keep])), 1e-30))
    resid_px = math.sqrt(float(np.median(r2_full)) / 0.455) * focal_px  # chi2(1) median -> rms
    E = _e_matrix(e / np.linalg.norm(e))
    common = dict(inliers=n_in, f_ratio=f_ratio, essential=E, **base)
    if not f_ratio > cfg.rotation_f_ratio:
        rres = math.sqrt(float(np.median(r2_rot)) / 1.386) * focal_px  # chi2(2) median -> rms
        return RelativePose(PoseStatus.PURE_ROTATION, theta=float(wrap_angle(th_rot)), residual_px=rres, **common)

    # cheirality: points in front of the goal camera have a_i = |c| / Z_goal,i > 0
    a, _, _ = _per_point_a(theta, psi, g, c)
    if np.median(a) < 0:
        psi, a = psi + math.pi, -a
    if np.mean(a > 0) < 0.5:
        return RelativePose(PoseStatus.DEGENERATE, theta=float(wrap_angle(theta)), **common)
    if scale is ScaleConvention.MEDIAN_DEPTH:
        k = float(np.median(a))  # |c| / median(Z_goal)
    else:
        below = np.flatnonzero(g[:, 1] > cfg.floor_min_y)
        if len(below) < 3:
            return RelativePose(PoseStatus.DEGENERATE, theta=float(wrap_angle(theta)), **common)
        # a_i / y_i = |c| / Y_i (Y_i: point height below the camera). The points lowest in the
        # image are floor points (Y_i = camera height) unless something stands close to the camera.
        low = below[np.argsort(-g[below, 1])][: max(3, int(math.ceil(cfg.floor_fraction * len(below))))]
        k = float(np.median(a[low] / g[low, 1]))
    cX, cZ = k * math.sin(psi), k * math.cos(psi)
    pose = RelativePose(
        PoseStatus.OK, theta=float(wrap_angle(theta)), x_s=cZ, z_s=-cX, residual_px=resid_px, **common
    )
    # 5. a single plane (a wall): the images allow the homography's two poses. The essential matrix
    # lands on (about) one of them; keep it unless the wall would then face away from its points.
    sols = _plane_solutions(g, c, 2.0 * thr, cfg) if scale is ScaleConvention.MEDIAN_DEPTH else []
    if all(p.t_over_d < cfg.plane_min_t_over_d for p in sols):
        return pose
    sols.sort(key=lambda p: abs(wrap_angle(p.theta - pose.theta)))
    visible = [p for p in sols if p.visible >= cfg.plane_min_visible]
    if not visible:
        return pose
    pose = replace(pose, plane_solutions=tuple(visible))
    return pose.with_plane_solution(visible[0]) if visible[0] is not sols[0] else pose


def _plane_solutions(g: np.ndarray, c: np.ndarray, thr: float, cfg: RelativePoseConfig) -> list[PlaneSolution]:
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


# ============================================================================ 2 points
def two_point_candidates(goal_n: np.ndarray, cur_n: np.ndarray, min_abs_y: float = 0.02) -> list[tuple[float, float, float]]:
    """All planar poses ``(theta, x_s, z_s)`` that 2 matches allow (docs/theory.md section 3).

    Each point's vertical coordinate gives its depth ratio ``s_i = y_goal / y_cur`` (constant camera
    height), so for a heading ``theta`` the point yields ``q_i = c / Z_goal,i`` in closed form; both
    ``q_i`` must be parallel: ``K + P cos(theta) + Q sin(theta) = 0`` — at most two roots. Roots that
    put a point behind the goal camera are dropped. Scale: ``lambda`` = harmonic mean of the two
    goal depths (``|c| / lambda = (a_1 + a_2) / 2``). Returns 0, 1 or 2 candidates.
    """
    goal_n = np.asarray(goal_n, dtype=np.float64).reshape(-1, 2)[:2]
    cur_n = np.asarray(cur_n, dtype=np.float64).reshape(-1, 2)[:2]
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
        goal_n = np.asarray(goal_n, dtype=np.float64).reshape(-1, 2)
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
