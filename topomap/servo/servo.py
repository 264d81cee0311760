"""``AppearanceServo``: matched points in, velocity command out (docs/theory.md section 3).

One control step chains the three parts of :mod:`topomap.servo`:

1. :func:`~topomap.servo.relpose.relative_pose` — scaled planar pose of the current camera w.r.t.
   the goal camera from the matched pixels;
2. :class:`~topomap.servo.disturbance.DisturbanceObserver` — ``d_omega`` from the heading rate, the
   scaled forward speed ratio for the scale-free law;
3. :func:`~topomap.servo.laws.unicycle_law` or :func:`~topomap.servo.laws.omni_law`.

The servo never sees a ground-truth pose: only pixels, intrinsics, the control period and the command
that was actually applied. It holds the integral state and the observer between steps; call
:meth:`AppearanceServo.retarget` when the goal image changes (the next subgoal of a route) so the pose
references restart while the disturbance estimates carry over.
"""

from __future__ import annotations

import enum
import logging
import math
from dataclasses import dataclass, replace

import numpy as np

from topomap.camera import CameraIntrinsics
from topomap.config import ServoConfig
from topomap.errors import ConfigError
from topomap.motion import STOP, Command, VehicleKind, vehicle_kind, wrap_angle
from topomap.servo.homography import choose_plane_solution
from topomap.servo.pose import PoseStatus, RelativePose
from topomap.servo.relpose import relative_pose_with_scales
from topomap.servo.laws import LawState, omni_law, unicycle_law
from topomap.servo.disturbance import DisturbanceEstimate, DisturbanceObserver

__all__ = ["ServoStatus", "ServoOutput", "AppearanceServo", "PoseWindow"]

log = logging.getLogger(__name__)

#: While blind (holding or turning toward the goal) speeds stay below this fraction of max_speed_mps.
BLIND_SPEED_FRACTION = 0.3


class PoseWindow:
    """The median of the relative poses measured in the last ``size`` control periods, each moved on
    to now by the motion predicted since it was measured: the applied command through the
    observer's ``kappa``, drift and ``d_omega`` (docs/servo.md, "Pose window"). Facing a close wall
    one image's scaled position scatters by a tenth of a metre and now and then by metres; the
    component-wise median of a few predicted poses removes both while the prediction keeps it from
    lagging the motion. Hand-written: a few lines over a list, no filter library has this window."""

    def __init__(self, size: int):
        self.size = int(size)
        self._poses: list[np.ndarray] = []  # (x_s, z_s, theta, age in periods) in the goal frame

    def clear(self) -> None:
        self._poses.clear()

    def predict(self, applied: Command | None, est: DisturbanceEstimate, dt: float) -> None:
        """Move every held pose by the motion of one period under ``applied``; forget those older
        than the window."""
        self._poses = [p for p in self._poses if p[3] + 1 < self.size]
        kappa = est.kappa if math.isfinite(est.kappa) else 0.0
        cmd = applied if applied is not None else STOP
        nu_f, nu_h = kappa * cmd.v_f + est.mu_f, kappa * cmd.v_h + est.mu_h  # scaled, body frame
        turn = (cmd.omega + est.d_omega) * dt
        for p in self._poses:
            c, s = math.cos(p[2]), math.sin(p[2])
            p += (dt * (c * nu_f - s * nu_h), dt * (s * nu_f + c * nu_h), turn, 1.0)

    def add(self, x_s: float, z_s: float, theta: float) -> tuple[float, float, float]:
        """Hold this period's measurement; returns the window's median pose."""
        self._poses.append(np.array([x_s, z_s, theta, 0.0]))
        if len(self._poses) == 1:
            return x_s, z_s, theta
        poses = np.array(self._poses)
        turns = np.arctan2(np.sin(poses[:, 2] - theta), np.cos(poses[:, 2] - theta))  # about the newest heading
        return float(np.median(poses[:, 0])), float(np.median(poses[:, 1])), wrap_angle(theta + float(np.median(turns)))


class ServoStatus(str, enum.Enum):
    """What the servo did in one step."""

    APPROACHING = "approaching"  # driving toward the goal pose
    ALIGNING = "aligning"  # at the goal position (or translation unobservable): fixing the heading
    CONVERGED = "converged"  # within position_tol_m and heading_tol_deg (estimated)
    LOST = "lost"  # no usable geometry this step: the command only cancels the estimated disturbance


@dataclass(frozen=True)
class ServoOutput:
    """One control step.

    ``command``: the velocity to apply for the next period; ``position_error_s``: estimated distance
    to the goal ``rho / lambda`` (0 when the images show no translation, NaN when lost);
    ``position_error_m``: the same times the goal's scale (``retarget``; default ``nominal_scale_m``);
    ``heading_error_rad``: estimated relative heading (NaN when lost); ``inliers``: matches that
    agree with the planar motion; ``converged``: both errors below the configured tolerances;
    ``floor_distance_h``: the distance to the goal in camera heights, from the lowest matched points
    taken as floor (the camera-height convention of the same solve, before a wall's plane is
    chosen; NaN without a translating pose or floor points) — metric given the camera's height,
    independent of the goal's scale.
    """

    command: Command
    status: ServoStatus
    pose: RelativePose
    position_error_s: float
    position_error_m: float
    heading_error_rad: float
    inliers: int
    converged: bool
    disturbance: DisturbanceEstimate
    floor_distance_h: float = math.nan


class AppearanceServo:
    """Stateful appearance servo for one vehicle kind; see the module docstring.

    ``vehicle``: ``"unicycle"`` / ``"omni"`` or a :class:`~topomap.motion.VehicleKind`;
    ``config``: a :class:`~topomap.config.ServoConfig` (``SERVO_PRESETS``).
    """

    def __init__(self, vehicle: str | VehicleKind = VehicleKind.UNICYCLE, config: ServoConfig | None = None):
        self.vehicle = vehicle_kind(vehicle)
        self.config = config or ServoConfig()
        if not isinstance(self.config, ServoConfig):
            raise ConfigError(f"servo config must be a ServoConfig, got {type(self.config).__name__}")
        self.observer = DisturbanceObserver(self.config.observer, 1.0 / self.config.nominal_scale_m)
        self.state = LawState()
        self.steps = 0
        # facing a wall the images allow two poses; normals of the goal's wall seen from other
        # viewpoints pick one (retarget)
        self.wall_normals: tuple[float, ...] = ()
        self.scale_m = self.config.nominal_scale_m  # metres per scaled unit at this goal (best guess)
        self.window = PoseWindow(self.config.pose_window)

    # ------------------------------------------------------------------ lifecycle
    def retarget(self, wall_normals=(), scale_m: float | None = None, heading_prior_rad: float | None = None) -> None:
        """A new goal image: restart pose references, keep the disturbance estimates.

        ``wall_normals``: angles [rad] of the goal wall's normal that other views of the goal image
        allow (:func:`~topomap.servo.homography.wall_normals`); facing a single wall they decide
        between the two poses the images allow. ``scale_m``: the goal's scale (metres per scaled
        unit, e.g. its median depth) when known; it turns the estimated distance into metres
        (``position_error_m``, convergence) and sets the laws' metric radii and gains; default
        ``nominal_scale_m``. ``heading_prior_rad``: the heading relative to the new goal predicted
        from the images so far (see :meth:`DisturbanceObserver.reset_target`): while the new goal's
        image does not match yet, :meth:`reacquire_command` turns toward it instead of holding.

        The unicycle keeps its along-track integral (a forward disturbance lives in the vehicle
        frame); the omnidirectional integral is expressed in the old goal's frame and restarts.
        """
        self.observer.reset_target(heading_prior_rad)
        self.window.clear()
        self.wall_normals = tuple(float(n) for n in wall_normals)
        self.scale_m = float(scale_m) if scale_m is not None else self.config.nominal_scale_m
        keep = self.state.integral if self.vehicle is VehicleKind.UNICYCLE else (0.0, 0.0)
        self.state = LawState(integral=keep)

    def rescale(self, scale_m: float) -> None:
        """The same goal at another scale (metres per scaled unit): measured better than at
        :meth:`retarget`; pose references and disturbance estimates kept."""
        if not (math.isfinite(scale_m) and scale_m > 0):
            raise ConfigError(f"scale_m={scale_m} must be a positive number of metres")
        self.scale_m = float(scale_m)

    def reset(self) -> None:
        """Forget everything (disturbances included)."""
        self.observer = DisturbanceObserver(self.config.observer, 1.0 / self.config.nominal_scale_m)
        self.state = LawState()
        self.steps = 0
        self.wall_normals = ()
        self.scale_m = self.config.nominal_scale_m
        self.window = PoseWindow(self.config.pose_window)

    # ------------------------------------------------------------------ one step
    def step(
        self,
        matched_cur_px: np.ndarray,
        matched_goal_px: np.ndarray,
        camera: CameraIntrinsics,
        dt: float,
        last_command: Command | None = None,
        goal_camera: CameraIntrinsics | None = None,
        measured: RelativePose | None = None,
        features_within_s: float | None = None,
    ) -> ServoOutput:
        """One control step.

        ``matched_cur_px, matched_goal_px``: (N, 2) pixels of the same features in the current and
        the goal image (row i matches row i); ``camera``: intrinsics of the current image
        (``goal_camera`` of the goal image, default the same); ``dt``: time since the previous step
        [s]; ``last_command``: the command applied since the previous step (None on the first);
        ``measured``: a pose measured otherwise for this image (the floor's alignment,
        :mod:`topomap.servo.floor`; status OK, position at this servo's scale): used instead of the
        features' pose, which still gives the floor reading — unless ``features_within_s`` is given
        and the features' pose lies within that distance of it (scaled units): where the two agree,
        the features are the finer witness.
        """
        if not (math.isfinite(dt) and dt > 0):
            raise ConfigError(f"control period dt={dt} must be a positive number of seconds")
        cfg = self.config
        self.steps += 1
        # the floor's distance comes from the same solve: a metric check of the goal's scale
        pose, _, rho_floor = relative_pose_with_scales(matched_cur_px, matched_goal_px, camera, cfg.geometry,
                                                       goal_camera=goal_camera)
        floor_s = rho_floor if rho_floor is not None else math.nan
        pose = choose_plane_solution(pose, self.wall_normals)
        if measured is not None and not (features_within_s is not None and pose.status is PoseStatus.OK
                                         and math.hypot(pose.x_s - measured.x_s, pose.z_s - measured.z_s) < features_within_s):
            pose = measured
        self.window.predict(last_command, self.observer.estimate, dt)  # the held poses, moved on to now
        if pose.status is PoseStatus.OK:
            x_s, z_s = pose.x_s, pose.z_s
        elif pose.status is PoseStatus.PURE_ROTATION:
            x_s = z_s = 0.0  # the translation is below what the images resolve: at the goal position
        else:
            est = self.observer.update(dt, last_command, None, None)
            log.debug("servo step %d: no geometry (%s, %d inliers)", self.steps, pose.status.value, pose.inliers)
            return ServoOutput(self.reacquire_command(est), ServoStatus.LOST, pose, math.nan, math.nan, math.nan,
                               pose.inliers, False, est, floor_s)
        theta = pose.theta
        est = self.observer.update(dt, last_command, theta, pose.position_s if pose.status is PoseStatus.OK else None)
        # the laws steer by the window's median pose; what the step reports (distance, heading,
        # convergence) stays this image's measurement: arrival tests count consecutive images as
        # independent witnesses, which a median's consecutive values are not
        x_w, z_w, theta_w = self.window.add(x_s, z_s, theta)
        # the laws' metric radii and gains at this goal's scale (the observer keeps its own)
        law_cfg = cfg if self.scale_m == cfg.nominal_scale_m else replace(cfg, nominal_scale_m=self.scale_m)
        if self.vehicle is VehicleKind.UNICYCLE:
            cmd, self.state = unicycle_law(
                x_w, z_w, theta_w, law_cfg, self.state, dt, d_omega_hat=est.d_omega, kappa_hat=est.kappa, mu_hat=est.mu_f
            )
        else:
            cmd, self.state = omni_law(x_w, z_w, theta_w, law_cfg, self.state, dt, d_omega_hat=est.d_omega)
        rho_s = math.hypot(x_s, z_s)
        dist_m = rho_s * self.scale_m
        converged = dist_m < cfg.position_tol_m and abs(theta) < math.radians(cfg.heading_tol_deg)
        if converged:
            status = ServoStatus.CONVERGED
        elif pose.status is PoseStatus.PURE_ROTATION or self.state.aligning:
            status = ServoStatus.ALIGNING
        else:
            status = ServoStatus.APPROACHING
        return ServoOutput(cmd.for_vehicle(self.vehicle), status, pose, rho_s, dist_m, theta, pose.inliers, converged, est,
                           floor_s)

    def age(self, seconds: float) -> None:
        """``seconds`` passed without a :meth:`step` (searching, backing off): the disturbance
        estimates grow less certain (:meth:`DisturbanceObserver.age`)."""
        self.observer.age(seconds)

    def observe_turn(self, dt: float, applied: Command | None, turned_rad: float | None) -> DisturbanceEstimate:
        """The turn measured between two consecutive images (a visual gyro), ``dt`` [s] apart under
        ``applied``: corrects the disturbance estimate while no goal is in view
        (:meth:`DisturbanceObserver.observe_turn`); returns the estimate."""
        return self.observer.observe_turn(dt, applied, turned_rad)

    def reacquire_command(self, est: DisturbanceEstimate) -> Command:
        """While blind: hold position (:meth:`hold_command`) and turn in place toward the goal's
        heading as the observer dead-reckons it (commanded turns and the estimated d_omega since the
        last image): a unicycle manoeuvring near its goal loses the view by swinging its heading."""
        cmd = self.hold_command(est)
        cfg = self.config
        if cmd is STOP or not math.isfinite(est.theta) or abs(est.theta) < math.radians(cfg.heading_tol_deg):
            return cmd
        turn = Command(cmd.v_f, cmd.v_h, -cfg.k_theta * est.theta - est.d_omega).clipped(
            BLIND_SPEED_FRACTION * cfg.max_speed_mps, cfg.max_turn_rps)
        return turn.for_vehicle(self.vehicle)

    def hold_command(self, est: DisturbanceEstimate) -> Command:
        """Stand still while blind: cancel the disturbances estimated so far (STOP before the
        observer has any). Under a turning bias a plain STOP would spin the camera away from the
        view it needs to recover."""
        if not self.config.compensate or not est.ready:
            return STOP
        limit_v, limit_w = BLIND_SPEED_FRACTION * self.config.max_speed_mps, self.config.max_turn_rps
        v_f = v_h = 0.0
        if math.isfinite(est.kappa) and est.kappa > 1e-6:  # drift mu [lambda/s] over kappa [1/m] -> m/s
            v_f, v_h = -est.mu_f / est.kappa, -est.mu_h / est.kappa
        cmd = Command(v_f, v_h, -est.d_omega).clipped(limit_v, limit_w)
        return cmd.for_vehicle(self.vehicle)

    def reconfigure(self, **changes) -> None:
        """Change configuration fields in place, keeping the disturbance estimates and the law state
        (e.g. a wide docking radius for a route's waypoints, the precise one for its goal)."""
        if "observer" in changes or "nominal_scale_m" in changes:
            raise ConfigError("the observer settings and the nominal scale cannot change while running; make a new servo")
        self.config = replace(self.config, **changes)
        if self.config.pose_window != self.window.size:
            self.window = PoseWindow(self.config.pose_window)
