"""The teach run: a ground-truth path follower drives a route and records the camera images.

This is the "human driver" of teach-and-repeat: it may use the true pose (nothing of it reaches the
navigation code). The run writes into ``out_dir``:

* ``0000.png, 0001.png, ...`` — an image every ``spacing_m`` of travel or ``turn_spacing_deg`` of turn;
* ``poses.csv`` — ``image,x,z,theta`` per image (ground truth; metres, radians);
* ``commands.csv`` — every command the driver sent (``t_s, dt_s, v_f, v_h, omega, after_image``),
  for the blind-replay baseline of the navigation benchmark;
* ``camera.yaml`` — the intrinsics, in the format ``topomap build --camera`` reads;
* ``world.json`` — the world, so the run can be replayed; ``teach.json`` — the run's settings.
"""

from __future__ import annotations

import csv
import json
import logging
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from topomap.camera import CameraIntrinsics
from topomap.errors import ConfigError, DatasetError
from topomap.motion import Command, wrap_angle
from topomap.sim.geometry import CAMERA_HEIGHT_M
from topomap.sim.conditions import Conditions, parse_conditions
from topomap.sim.simulator import Simulator, route_start
from topomap.sim.world import WaypointRoute, World

__all__ = ["TeachConfig", "TeachResult", "PurePursuit", "teach"]

log = logging.getLogger(__name__)


#: Most images one teach run records (a 200 m route every 1 cm); more is a typo in --spacing.
MAX_TEACH_IMAGES = 20_000


@dataclass(frozen=True)
class TeachConfig:
    """How the teach driver drives and when it takes a picture."""

    spacing_m: float = 0.25  # an image every this much travel [m] ...
    turn_spacing_deg: float = 10.0  # ... or this much turning [deg]
    speed_mps: float = 0.3  # cruising speed [m/s]
    max_turn_rps: float = 0.8  # turning-rate limit [rad/s]
    lookahead_m: float = 0.6  # pure-pursuit look-ahead distance [m]
    dt_s: float = 0.05  # control period [s]
    overlap_m: float = 3.0  # closed routes: drive this far past the start, so the start is seen again [m]

    def __post_init__(self) -> None:
        for name in ("spacing_m", "turn_spacing_deg", "speed_mps", "max_turn_rps", "lookahead_m", "dt_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ConfigError(f"teach {name}={v!r} must be a positive number")
        if self.overlap_m < 0:
            raise ConfigError("teach overlap_m must not be negative")
        if self.spacing_m > 5.0:
            raise ConfigError(f"teach spacing {self.spacing_m} m is too coarse for a map; use at most 5 m")
        # lower bounds: a teach run's images and control steps must stay countable
        for name, lo in (("spacing_m", 0.01), ("turn_spacing_deg", 0.5), ("speed_mps", 0.01), ("dt_s", 0.001)):
            if getattr(self, name) < lo:
                raise ConfigError(f"teach {name}={getattr(self, name)!r} is too small; use at least {lo}")
        if self.speed_mps > 5.0 or self.dt_s > 1.0:
            raise ConfigError("teach speed_mps must be at most 5 m/s and dt_s at most 1 s")


@dataclass(frozen=True)
class TeachResult:
    """Summary of a teach run: where it wrote, how many images, how far and how long it drove."""

    out_dir: Path
    route: str
    frames: int
    length_m: float  # distance driven [m]
    duration_s: float  # simulated time [s]
    collisions: int
    poses_path: Path
    camera_path: Path
    world_path: Path


class PurePursuit:
    """Pure-pursuit follower of a waypoint polyline (N, 2) [m] for a unicycle or omni vehicle.

    Steers towards the point ``lookahead_m`` ahead along the path (curvature ``2 sin(alpha)/L``),
    turns in place when that point is more than 60 degrees off the heading, slows down at the end;
    an omni vehicle also slides sideways onto the path. Progress along the path only moves forward,
    so a path that crosses itself is followed in order. Stops within 10 cm of the end, or when the
    end is behind and within 30 cm.
    """

    def __init__(
        self,
        waypoints: np.ndarray,
        lookahead_m: float = 0.6,
        speed_mps: float = 0.3,
        max_turn_rps: float = 0.8,
        omni: bool = False,
    ) -> None:
        p = np.asarray(waypoints, dtype=float)
        keep = np.concatenate([[True], np.linalg.norm(np.diff(p, axis=0), axis=1) > 1e-9])
        self.points = p[keep]
        if len(self.points) < 2:
            raise ConfigError("a path needs at least two distinct waypoints")
        seg = np.diff(self.points, axis=0)
        self._len = np.linalg.norm(seg, axis=1)
        self._cum = np.concatenate([[0.0], np.cumsum(self._len)])
        self.length_m = float(self._cum[-1])
        self.lookahead_m, self.speed_mps, self.max_turn_rps = float(lookahead_m), float(speed_mps), float(max_turn_rps)
        self.omni = bool(omni)
        self.progress_m = 0.0

    def point_at(self, s: float) -> np.ndarray:
        """The path point at arc length ``s`` [m] (clamped to the path)."""
        s = min(max(s, 0.0), self.length_m)
        i = min(int(np.searchsorted(self._cum, s, side="right")) - 1, len(self._len) - 1)
        f = (s - self._cum[i]) / self._len[i]
        return self.points[i] + f * (self.points[i + 1] - self.points[i])

    def _update_progress(self, xz: np.ndarray) -> None:
        # Closest point on the segments within [progress - 0.5, progress + 2] m.
        lo, hi = self.progress_m - 0.5, self.progress_m + 2.0
        best, best_s = math.inf, self.progress_m
        for i in range(len(self._len)):
            if self._cum[i + 1] < lo or self._cum[i] > hi:
                continue
            a, b = self.points[i], self.points[i + 1]
            t = float(np.clip(np.dot(xz - a, b - a) / self._len[i] ** 2, 0.0, 1.0))
            s = float(np.clip(self._cum[i] + t * self._len[i], lo, hi))
            d = float(np.linalg.norm(self.point_at(s) - xz))
            if d < best:
                best, best_s = d, s
        self.progress_m = max(self.progress_m, best_s)

    def command(self, pose) -> Command | None:
        """The command for ``pose = (x, z, theta)``, or None once the end of the path is reached."""
        x, z, theta = (float(v) for v in pose)
        xz = np.array([x, z])
        self._update_progress(xz)
        end = self.points[-1]
        to_end = float(np.linalg.norm(end - xz))
        remaining = self.length_m - self.progress_m
        c, s = math.cos(theta), math.sin(theta)
        ahead_of_end = c * (end[0] - x) + s * (end[1] - z)
        if remaining < 0.1 and (to_end < 0.1 or (ahead_of_end < 0 and to_end < 0.3)):
            return None
        target = self.point_at(self.progress_m + self.lookahead_m)
        dx, dy = c * (target[0] - x) + s * (target[1] - z), -s * (target[0] - x) + c * (target[1] - z)
        alpha = math.atan2(dy, dx)  # target bearing, positive to the left
        dist = math.hypot(dx, dy)
        if abs(alpha) > math.radians(60):
            return Command(0.0, 0.0, float(np.clip(2.0 * alpha, -self.max_turn_rps, self.max_turn_rps)))
        v = self.speed_mps
        if remaining < self.lookahead_m:
            v = min(v, 0.05 + 0.8 * to_end)
        kappa = 2.0 * math.sin(alpha) / max(dist, 1e-3)
        omega = v * kappa
        if abs(omega) > self.max_turn_rps:  # keep the curvature, slow down
            v *= self.max_turn_rps / abs(omega)
            omega = math.copysign(self.max_turn_rps, omega)
        v_h = 0.0
        if self.omni:  # slide onto the path: the offset of the closest path point, to the left
            p = self.point_at(self.progress_m)
            v_h = float(np.clip(-s * (p[0] - x) + c * (p[1] - z), -0.5 * self.speed_mps, 0.5 * self.speed_mps))
        return Command(float(v), v_h, float(omega))


def _route_path(route: WaypointRoute, overlap_m: float) -> np.ndarray:
    p = route.points
    if not route.closed or overlap_m <= 0:
        return p
    follower = PurePursuit(p)
    n = max(2, int(math.ceil(overlap_m / 0.25)) + 1)
    extra = [follower.point_at(s) for s in np.linspace(0.0, min(overlap_m, follower.length_m), n)[1:]]
    return np.vstack([p, extra])


def teach(
    world: World,
    route: str = "loop",
    out_dir: str | Path = "teach",
    *,
    config: TeachConfig | None = None,
    spacing_m: float | None = None,
    vehicle: str = "unicycle",
    disturbance: str = "none",
    camera: CameraIntrinsics | None = None,
    camera_height_m: float = CAMERA_HEIGHT_M,
    seed: int = 0,
    overwrite: bool = False,
    on_progress: Callable[[int, float], None] | None = None,
    conditions: str | Conditions | None = None,
) -> TeachResult:
    """Drive ``route`` of ``world`` with the ground-truth follower and record a teach run in ``out_dir``.

    ``spacing_m`` overrides ``config.spacing_m``; ``on_progress(frames, fraction_done)`` is called
    after each saved image; ``conditions``: how the run looks (:mod:`topomap.sim.conditions`,
    recorded in ``teach.json``; ``world.json`` keeps the world as generated). Raises :class:`DatasetError` if ``out_dir`` already holds a run (unless
    ``overwrite``) or if the route cannot be driven.
    """
    cfg = config or TeachConfig()
    cond = parse_conditions(conditions)
    if spacing_m is not None:
        cfg = TeachConfig(**{**asdict(cfg), "spacing_m": spacing_m})
    r = world.route(route)
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise DatasetError(f"output {out} exists and is not a folder; choose another -o")
    if (out / "poses.csv").exists() and not overwrite:
        raise DatasetError(f"{out} already holds a teach run; remove it, choose another output folder or overwrite it (--force)")
    try:
        out.mkdir(parents=True, exist_ok=True)
        for old in out.glob("[0-9][0-9][0-9][0-9]*.png"):
            old.unlink()
    except OSError as e:
        raise DatasetError(f"cannot write to {out}: {e.strerror or e}") from None

    path = _route_path(r, cfg.overlap_m)
    length = float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum())
    if length / cfg.spacing_m > MAX_TEACH_IMAGES:
        raise ConfigError(f"route {route!r} ({length:.0f} m) at one image every {cfg.spacing_m} m would take about "
                          f"{length / cfg.spacing_m:.0f} images, more than {MAX_TEACH_IMAGES}; use a larger --spacing")
    from topomap.motion import VehicleKind, vehicle_kind

    follower = PurePursuit(path, cfg.lookahead_m, cfg.speed_mps, cfg.max_turn_rps, omni=vehicle_kind(vehicle) is VehicleKind.OMNI)
    start = route_start(world, route)
    rows: list[tuple[str, float, float, float]] = []
    # (start time [s], dt [s], v_f, v_h, omega, index of the last image taken): the blind-replay baseline
    commands: list[tuple[float, float, float, float, float, int]] = []
    with Simulator(world, vehicle=vehicle, disturbance=disturbance, camera=camera, seed=seed,
                   start_pose=start, camera_height_m=camera_height_m, conditions=cond) as sim:
        gt = sim.ground_truth
        cam = sim.camera

        def snap() -> None:
            pose = gt.pose()
            name = f"{len(rows):04d}.png"
            img = gt.render()
            if not cv2.imwrite(str(out / name), cv2.cvtColor(img, cv2.COLOR_RGB2BGR)):
                raise DatasetError(f"cannot write image {out / name}; check the folder is writable")
            rows.append((name, pose.x, pose.z, pose.theta))
            if on_progress is not None:
                on_progress(len(rows), min(1.0, follower.progress_m / max(follower.length_m, 1e-9)))

        snap()
        last = np.array(gt.pose())
        driven = 0.0
        t_max = 3.0 * follower.length_m / cfg.speed_mps + 60.0
        stuck_since = None
        while True:
            pose = np.array(gt.pose())
            cmd = follower.command(pose)
            if cmd is None:
                break
            report = sim.robot.apply(cmd, cfg.dt_s)
            commands.append((report.time_s - report.dt_s, report.dt_s, cmd.v_f, cmd.v_h, cmd.omega, len(rows) - 1))
            new = np.array(gt.pose())
            step = float(np.linalg.norm(new[:2] - pose[:2]))
            driven += step
            if report.collided or step < 1e-4 and cmd.omega == 0.0:
                stuck_since = stuck_since if stuck_since is not None else report.time_s
            else:
                stuck_since = None
            if report.time_s > t_max or (stuck_since is not None and report.time_s - stuck_since > 5.0):
                raise DatasetError(
                    f"the teach driver could not finish route {route!r} (stuck at x={new[0]:.2f}, z={new[1]:.2f}); "
                    "check that the route stays on the free floor"
                )
            if (np.linalg.norm(new[:2] - last[:2]) >= cfg.spacing_m
                    or abs(wrap_angle(new[2] - last[2])) >= math.radians(cfg.turn_spacing_deg)):
                snap()
                last = new
        if np.linalg.norm(np.array(gt.pose())[:2] - last[:2]) > 0.05:
            snap()  # the end of the route
        duration = gt.time_s()
        collisions = gt.collisions

    poses_path = out / "poses.csv"
    with poses_path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["image", "x", "z", "theta"])
        for name, x, z, th in rows:
            w.writerow([name, f"{x:.6f}", f"{z:.6f}", f"{th:.6f}"])
    with (out / "commands.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t_s", "dt_s", "v_f", "v_h", "omega", "after_image"])
        for t, dt, vf, vh, om, k in commands:
            w.writerow([f"{t:.4f}", f"{dt:.4f}", f"{vf:.6f}", f"{vh:.6f}", f"{om:.6f}", k])
    camera_path = cam.save(out / "camera.yaml")
    world_path = world.save(out / "world.json")
    meta = {
        "route": route, "vehicle": str(vehicle), "disturbance": str(disturbance), "seed": seed,
        "camera_height_m": camera_height_m, "frames": len(rows), "length_m": round(driven, 3),
        "duration_s": round(duration, 3), "collisions": collisions, "config": asdict(cfg),
        "conditions": cond.to_dict(),
    }
    (out / "teach.json").write_text(json.dumps(meta, indent=2) + "\n")
    log.info("teach run of route %s: %d images over %.1f m in %s", route, len(rows), driven, out)
    return TeachResult(out, route, len(rows), driven, duration, collisions, poses_path, camera_path, world_path)
