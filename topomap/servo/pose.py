"""What a relative-pose reconstruction returns: its status, the scaled planar pose of the current
camera in the goal camera's frame, and the poses a single plane allows (docs/theory.md sections 1, 3).

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
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field, replace

import numpy as np

from topomap.config import ScaleConvention, scale_convention
from topomap.motion import wrap_angle

__all__ = ["PoseStatus", "ScaleConvention", "scale_convention", "PlaneSolution", "RelativePose"]


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


@dataclass(frozen=True)
class PlaneSolution:
    """One pose a planar-motion homography allows (:func:`~topomap.servo.homography.decompose_planar_homography`).

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
    (one or two, see :func:`~topomap.servo.homography.decompose_planar_homography`) — the reported pose is one of them, the one
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
    def position_s(self) -> np.ndarray:
        """(2,) float64 ``(x_s, z_s)``."""
        return np.array([self.x_s, self.z_s])

