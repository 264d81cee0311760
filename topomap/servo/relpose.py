"""Scaled planar relative pose of the current camera w.r.t. a target camera, from matched points.

docs/theory.md section 3 (static and dynamic appearance servoing). The camera rides at a constant height
with a horizontal optical axis, so the current camera differs from the target (goal) camera by a
rotation ``theta`` about the vertical axis and a horizontal translation. Frames, conventions and
the scale ``lambda``: :mod:`topomap.servo.pose`; solvers: :mod:`topomap.servo.essential`,
:mod:`topomap.servo.homography`, :mod:`topomap.servo.lm`.

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
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from topomap.camera import CameraIntrinsics
from topomap.config import RelativePoseConfig
from topomap.errors import points_array
from topomap.motion import wrap_angle
from topomap.servo.essential import (
    depth_ratio_direction,
    essential_matrix,
    per_point_depths,
    ransac_planar_essential,
    refine,
    reprojection_residuals,
    rotation_only_heading,
    rotation_y,
)
from topomap.servo.homography import plane_solutions
from topomap.servo.lm import LMFit, robust_lm
from topomap.servo.pose import PoseStatus, RelativePose, ScaleConvention, scale_convention

__all__ = ["relative_pose", "relative_pose_normalized", "relative_pose_with_scales"]


class _Rejected(Exception):
    """Internal: a stage found the matches unusable; ``fields`` complete the :class:`RelativePose`."""

    def __init__(self, status: PoseStatus, **fields):
        super().__init__(status.value)
        self.status, self.fields = status, fields


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
    the same). Never raises for bad geometry: the status says what went wrong; arrays of another
    shape or dtype (or of different lengths) raise :class:`~topomap.errors.ShapeError`.
    """
    cur = points_array(matched_cur_px, "matched_cur_px")
    goal = points_array(matched_goal_px, "matched_goal_px", rows=len(cur))
    goal_camera = goal_camera or camera
    f_px = 0.5 * (camera.fx + camera.fy)
    return relative_pose_normalized(camera.normalize(cur), goal_camera.normalize(goal), f_px, config)


def relative_pose_normalized(
    cur_n: np.ndarray, goal_n: np.ndarray, focal_px: float, config: RelativePoseConfig | None = None
) -> RelativePose:
    """:func:`relative_pose` on (N, 2) normalised coordinates; ``focal_px`` converts thresholds to pixels."""
    return _solve(points_array(cur_n, "cur_n"), points_array(goal_n, "goal_n", rows=len(cur_n)), focal_px,
                  config or RelativePoseConfig())[0]


def relative_pose_with_scales(
    matched_cur_px: np.ndarray,
    matched_goal_px: np.ndarray,
    camera: CameraIntrinsics,
    config: RelativePoseConfig | None = None,
    goal_camera: CameraIntrinsics | None = None,
) -> tuple[RelativePose, float | None, float | None]:
    """:func:`relative_pose` and the distance ``rho / lambda`` in two scale conventions, from one run:
    the configuration's own before the plane's choice (what ``plane_inlier_fraction=1`` reports) and
    the camera height's; each None where that pose would not be OK. Their ratio is a metric scale."""
    cur = points_array(matched_cur_px, "matched_cur_px")
    goal = points_array(matched_goal_px, "matched_goal_px", rows=len(cur))
    goal_camera = goal_camera or camera
    return _solve(camera.normalize(cur), goal_camera.normalize(goal), 0.5 * (camera.fx + camera.fy),
                  config or RelativePoseConfig())


def _rho(k: float, psi: float) -> float:
    """``RelativePose.rho_s`` of the pose at distance ``k`` in direction ``psi`` (the same arithmetic)."""
    cX, cZ = k * math.sin(psi), k * math.cos(psi)
    return math.hypot(cZ, -cX)


def _solve(cur_n: np.ndarray, goal_n: np.ndarray, focal_px: float,
           cfg: RelativePoseConfig) -> tuple[RelativePose, float | None, float | None]:
    """The pipeline: the pose, and the distances of :func:`relative_pose_with_scales`."""
    scale = scale_convention(cfg.scale)
    n = len(cur_n)
    mask = np.zeros(n, bool)  # filled once the inliers are final
    fields = dict(n_matches=n, scale=scale, inlier_mask=mask)
    try:
        finite = np.flatnonzero(np.isfinite(cur_n).all(axis=1) & np.isfinite(goal_n).all(axis=1))
        if len(finite) < max(3, cfg.min_inliers):
            raise _Rejected(PoseStatus.TOO_FEW_POINTS)
        g_all, c_all = goal_n[finite], cur_n[finite]
        thr = cfg.ransac_px / focal_px
        e, theta0, t0, inl = _essential_stage(g_all, c_all, thr, cfg)
        theta, psi, fit, inl = _refine_stage(g_all, c_all, inl, theta0, t0, thr, focal_px, cfg)
        mask[finite[inl]] = True
        g, c = g_all[inl], c_all[inl]
        r2_full = np.sum(fit.fun.reshape(-1, 2) ** 2, axis=1)
        f_ratio, th_rot, r2_rot = _translation_test(g, c, r2_full, thr)
        fields.update(inliers=int(inl.sum()), f_ratio=f_ratio, essential=essential_matrix(e / np.linalg.norm(e)))
        if not f_ratio > cfg.rotation_f_ratio:
            rres = math.sqrt(float(np.median(r2_rot)) / 1.386) * focal_px  # chi2(2) median -> rms
            pose = RelativePose(PoseStatus.PURE_ROTATION, theta=float(wrap_angle(th_rot)), residual_px=rres, **fields)
            return pose, None, None
        k_depth, k_floor, psi = _scale_stage(theta, psi, g, c, cfg)
        k = k_depth if scale is ScaleConvention.MEDIAN_DEPTH else k_floor
        if k is None:  # too few points below the horizon to find the floor
            raise _Rejected(PoseStatus.DEGENERATE, theta=float(wrap_angle(theta)))
    except _Rejected as r:
        return RelativePose(r.status, **{**fields, **r.fields}), None, None
    resid_px = math.sqrt(float(np.median(r2_full)) / 0.455) * focal_px  # chi2(1) median -> rms
    cX, cZ = k * math.sin(psi), k * math.cos(psi)
    pose = RelativePose(PoseStatus.OK, theta=float(wrap_angle(theta)), x_s=cZ, z_s=-cX, residual_px=resid_px, **fields)
    return _plane_stage(pose, g, c, thr, scale, cfg), pose.rho_s, None if k_floor is None else _rho(k_floor, psi)


def _essential_stage(g_all: np.ndarray, c_all: np.ndarray, thr: float, cfg: RelativePoseConfig):
    """1-2. Planar E by 3-point MSAC, decomposed: ``(e (4,), theta0, t0 (2,), inlier mask)``."""
    e, theta0, t0, inl = ransac_planar_essential(
        g_all, c_all, thr, confidence=cfg.ransac_confidence, max_iters=cfg.ransac_max_iters,
        min_iters=min(cfg.ransac_min_iters, cfg.ransac_max_iters), seed=cfg.seed,
    )
    if inl.sum() < cfg.min_inliers:
        raise _Rejected(PoseStatus.TOO_FEW_INLIERS, inliers=int(inl.sum()))
    if np.count_nonzero(np.abs(g_all[inl][:, 1]) > cfg.min_abs_y) < 3:
        # every row of the design matrix needs y != 0: points on the horizon fix nothing
        raise _Rejected(PoseStatus.DEGENERATE, inliers=int(inl.sum()))
    return e, theta0, t0, inl


def _refine_stage(g_all, c_all, inl: np.ndarray, theta0: float, t0: np.ndarray, thr: float, focal_px: float,
                  cfg: RelativePoseConfig) -> tuple[float, float, LMFit, np.ndarray]:
    """3. Reprojection error over ``(theta, direction psi of c)``, ``a_i`` eliminated; matches the full
    model cannot explain (epipolar-consistent but wrong in y) leave the inliers and it refits once.
    Returns ``(theta, psi, fit, inlier mask)``."""
    g, c = g_all[inl], c_all[inl]
    c_hat0 = -rotation_y(theta0).T @ np.array([t0[0], 0.0, t0[1]])
    psis = [math.atan2(c_hat0[0], c_hat0[2])]
    psi_pca = depth_ratio_direction(theta0, g, c, cfg.min_abs_y)
    if psi_pca is not None:
        psis.append(psi_pca)
    fit = refine(g, c, theta0, psis, thr)
    theta, psi = float(fit.x[0]), float(fit.x[1])
    r = fit.fun.reshape(-1, 2)
    good = np.hypot(r[:, 0], r[:, 1]) * focal_px < 2.0 * cfg.ransac_px
    if good.sum() < cfg.min_inliers:
        raise _Rejected(PoseStatus.TOO_FEW_INLIERS, inliers=int(good.sum()))
    if not good.all():
        inl[np.flatnonzero(inl)[~good]] = False
        fit = refine(g[good], c[good], theta, [psi], thr)
        theta, psi = float(fit.x[0]), float(fit.x[1])
    return theta, psi, fit, inl


def _translation_test(g: np.ndarray, c: np.ndarray, r2_full: np.ndarray, thr: float) -> tuple[float, float, np.ndarray]:
    """4. Translation significance against the rotation-only model on the same inliers:
    ``(f_ratio, rotation-only heading, its squared residuals (N,))``.

    Per point, the rotation model has one parameter less (the depth a_i); under a pure rotation
    r2_rot - r2_full and r2_full have about the same distribution, so their means' ratio is ~1.
    Trimmed means, because a few outliers lying along epipolar lines survive (a_i absorbs them)."""
    th_rot = robust_lm(lambda p: reprojection_residuals(p[0], 0.0, g, c, with_a=False), [rotation_only_heading(g, c)], thr).x[0]
    r2_rot = np.sum(reprojection_residuals(th_rot, 0.0, g, c, with_a=False).reshape(-1, 2) ** 2, axis=1)
    diff = r2_rot - r2_full
    keep = diff <= np.quantile(diff, 0.9)  # trimmed: the surviving outliers have the largest diff
    f_ratio = float(np.mean(diff[keep]) / max(float(np.mean(r2_full[keep])), 1e-30))
    return f_ratio, th_rot, r2_rot


def _scale_stage(theta: float, psi: float, g: np.ndarray, c: np.ndarray,
                 cfg: RelativePoseConfig) -> tuple[float, float | None, float]:
    """The sign of ``c`` by cheirality and ``|c| / lambda`` in both scale conventions:
    ``(k median depth, k camera height or None without floor points, psi)``."""
    # cheirality: points in front of the goal camera have a_i = |c| / Z_goal,i > 0
    a, _, _ = per_point_depths(theta, psi, g, c)
    if np.median(a) < 0:
        psi, a = psi + math.pi, -a
    if np.mean(a > 0) < 0.5:
        raise _Rejected(PoseStatus.DEGENERATE, theta=float(wrap_angle(theta)))
    k_depth = float(np.median(a))  # |c| / median(Z_goal)
    below = np.flatnonzero(g[:, 1] > cfg.floor_min_y)
    if len(below) < 3:
        return k_depth, None, psi
    # a_i / y_i = |c| / Y_i (Y_i: point height below the camera). The points lowest in the
    # image are floor points (Y_i = camera height) unless something stands close to the camera.
    low = below[np.argsort(-g[below, 1])][: max(3, int(math.ceil(cfg.floor_fraction * len(below))))]
    return k_depth, float(np.median(a[low] / g[low, 1])), psi


def _plane_stage(pose: RelativePose, g: np.ndarray, c: np.ndarray, thr: float, scale: ScaleConvention,
                 cfg: RelativePoseConfig) -> RelativePose:
    """5. A single plane (a wall): the images allow the homography's two poses. The essential matrix
    lands on (about) one of them; keep it unless the wall would then face away from its points."""
    sols = plane_solutions(g, c, 2.0 * thr, cfg) if scale is ScaleConvention.MEDIAN_DEPTH else []
    if all(p.t_over_d < cfg.plane_min_t_over_d for p in sols):
        return pose
    sols.sort(key=lambda p: abs(wrap_angle(p.theta - pose.theta)))
    visible = [p for p in sols if p.visible >= cfg.plane_min_visible]
    if not visible:
        return pose
    pose = replace(pose, plane_solutions=tuple(visible))
    return pose.with_plane_solution(visible[0]) if visible[0] is not sols[0] else pose
