"""The simulator facade, split along the boundary between what a robot knows and what only the world knows.

* :attr:`Simulator.robot` (:class:`Robot`) is all that navigation code gets: the camera intrinsics,
  ``render()`` (a plain image array) and ``apply(command, dt)`` (a :class:`StepReport` with a
  collision flag, no pose). A real robot would offer the same three things (:class:`RobotInterface`).
* :attr:`Simulator.ground_truth` (:class:`GroundTruth`) hands out the true pose, the realised
  disturbance and the trajectory, for scoring and for the teach run's driver only.

Usage::

    sim = Simulator(default_world(), vehicle="unicycle", disturbance="bias", seed=0)
    robot = sim.robot
    image = robot.render()
    report = robot.apply(Command(v_f=0.3, omega=0.1), dt=0.1)
    sim.ground_truth.pose()   # scoring only
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from topomap.camera import CameraIntrinsics
from topomap.errors import ConfigError
from topomap.motion import Command, VehicleKind, vehicle_kind
from topomap.sim.conditions import Conditions, apply_conditions, moved_world, parse_conditions
from topomap.sim.geometry import CAMERA_HEIGHT_M, Pose
from topomap.sim.render import Renderer, make_renderer
from topomap.sim.vehicle import DisturbanceConfig, Vehicle, VehicleConfig, parse_disturbance
from topomap.sim.world import World

__all__ = ["Simulator", "Robot", "RobotInterface", "GroundTruth", "StepReport", "default_camera", "route_start"]


def default_camera(width: int = 320, height: int = 240, hfov_deg: float = 60.0) -> CameraIntrinsics:
    """The simulator's pinhole camera: square pixels, centred principal point, ``hfov_deg`` field of view."""
    from dataclasses import replace

    return replace(CameraIntrinsics.default(width, height, hfov_deg), source="simulator")


def route_start(world: World, route: str = "loop") -> Pose:
    """The first waypoint of ``route``, heading along its first segment."""
    p = world.route(route).points
    return Pose(float(p[0, 0]), float(p[0, 1]), math.atan2(p[1, 1] - p[0, 1], p[1, 0] - p[0, 0]))


@dataclass(frozen=True)
class StepReport:
    """What the robot learns from executing a command: no pose, only what its own sensors could tell.

    ``collided``: the vehicle touched a wall during the step and stopped translating;
    ``saturated``: the command exceeded the vehicle's limits and was clipped;
    ``time_s``: the robot's clock after the step [s]; ``dt_s``: the step length [s].
    """

    collided: bool
    saturated: bool
    time_s: float
    dt_s: float


@runtime_checkable
class RobotInterface(Protocol):
    """What navigation may use: a simulated :class:`Robot` or a real robot's driver (optionally
    also ``camera_height_m``, the camera's mounting height, which makes goal distances metric)."""

    camera: CameraIntrinsics
    kind: VehicleKind

    def render(self) -> np.ndarray: ...

    def apply(self, command: Command, dt: float) -> StepReport: ...


class Robot:
    """The robot side of the simulator: camera intrinsics, images and velocity commands. No pose."""

    __slots__ = ("_sim",)

    def __init__(self, sim: Simulator) -> None:
        self._sim = sim

    @property
    def camera(self) -> CameraIntrinsics:
        """Intrinsics the images obey (``K``, size)."""
        return self._sim.camera

    @property
    def kind(self) -> VehicleKind:
        """Unicycle or omnidirectional: which command channels the vehicle has."""
        return self._sim.vehicle_config.kind

    @property
    def camera_height_m(self) -> float:
        """How high the camera is mounted above the floor [m] (fixed; a real robot knows it too)."""
        return self._sim.camera_height_m

    def render(self) -> np.ndarray:
        """The current camera image: a fresh ``(H, W, 3) uint8`` RGB array (nothing attached)."""
        return self._sim._image(Pose(*self._sim._vehicle.pose))

    def apply(self, command: Command, dt: float) -> StepReport:
        """Execute ``command`` for ``dt`` seconds (the vehicle adds its unknown disturbance)."""
        if not isinstance(command, Command):
            raise ConfigError(f"apply() needs a topomap.motion.Command, got {type(command).__name__}")
        collided, saturated = self._sim._vehicle.advance(command, dt)
        self._sim._log()
        return StepReport(bool(collided), bool(saturated), float(self._sim._vehicle.time_s), float(dt))


class GroundTruth:
    """The world side: true pose, disturbance and trajectory. For scoring and teaching only."""

    __slots__ = ("_sim",)

    def __init__(self, sim: Simulator) -> None:
        self._sim = sim

    @property
    def world(self) -> World:
        return self._sim.world

    def pose(self) -> Pose:
        """True pose ``(x, z, theta)`` [m, m, rad], theta in ``(-pi, pi]``."""
        return Pose(*(float(v) for v in self._sim._vehicle.pose))

    def set_pose(self, pose: tuple[float, float, float]) -> None:
        """Teleport the vehicle (experiments and tests)."""
        p = np.array(pose, dtype=float)
        if p.shape != (3,) or not np.isfinite(p).all():
            raise ConfigError(f"pose {pose!r} must be three finite numbers x, z, theta")
        self._sim._vehicle.pose = p
        self._sim._log()

    def time_s(self) -> float:
        return float(self._sim._vehicle.time_s)

    def disturbance(self) -> np.ndarray:
        """The disturbance ``d = (d_f, d_h, d_omega)`` of the last integration step (3,) float64."""
        return self._sim._vehicle.last_d.copy()

    def disturbance_log(self) -> np.ndarray:
        """(N, 8) float64, one row per integration step: ``t0, h, u_f, u_h, u_omega, d_f, d_h, d_omega``.

        ``t0`` the step's start [s], ``h`` its length [s], ``u`` the command after saturation,
        ``d`` the disturbance held over the step — the truth a disturbance observer is scored against.
        """
        return np.array(self._sim._vehicle.log, dtype=float).reshape(-1, 8)

    def clearance(self) -> float:
        """Distance from the vehicle's centre to the nearest wall [m]."""
        return self._sim._vehicle.clearance()

    @property
    def collisions(self) -> int:
        """Number of commands during which the vehicle hit a wall."""
        return self._sim._vehicle.collisions

    def trajectory(self) -> np.ndarray:
        """(N, 4) float64 rows ``t, x, z, theta`` logged after every command (and at the start)."""
        return np.array(self._sim._trajectory, dtype=float)

    def render(self, pose: tuple[float, float, float] | None = None) -> np.ndarray:
        """The image at ``pose`` (default: the true pose) without moving the vehicle (under the
        simulator's conditions, like the robot's images)."""
        return self._sim._image(Pose(*(self._sim._vehicle.pose if pose is None else pose)))


class Simulator:
    """A world, a camera-carrying vehicle with unknown input disturbances, and a renderer.

    ``vehicle``: ``"unicycle"`` / ``"omni"`` / :class:`VehicleKind` / :class:`VehicleConfig`;
    ``disturbance``: a preset name, ``"preset,key=value"`` spec or :class:`DisturbanceConfig`;
    ``camera``: intrinsics with a size (default: :func:`default_camera`); ``seed``: the random
    walk's seed; ``start_pose``: default the start of the ``loop`` route (or of the first route);
    ``renderer``: a backend name of :data:`topomap.sim.render.RENDERERS`, or a :class:`Renderer` of
    this world (its camera is used; it is not closed with the simulator, so one can serve many);
    ``conditions``: how the run looks (:mod:`topomap.sim.conditions`: a preset name, a
    ``"preset,key=value"`` spec or :class:`~topomap.sim.conditions.Conditions`) — light and moved
    panels go into the renderer the simulator creates, camera effects onto every image (noise
    seeded by ``seed``).
    """

    def __init__(
        self,
        world: World,
        vehicle: str | VehicleKind | VehicleConfig = "unicycle",
        disturbance: str | DisturbanceConfig | None = "none",
        camera: CameraIntrinsics | None = None,
        seed: int = 0,
        start_pose: tuple[float, float, float] | None = None,
        *,
        camera_height_m: float = CAMERA_HEIGHT_M,
        renderer: str | Renderer = "pybullet",
        conditions: str | Conditions | None = None,
    ) -> None:
        self.world = world
        self.vehicle_config = vehicle if isinstance(vehicle, VehicleConfig) else VehicleConfig(kind=vehicle_kind(vehicle))
        self.disturbance_config = parse_disturbance(disturbance)
        self._owns_renderer = isinstance(renderer, str)
        if not self._owns_renderer and getattr(renderer, "camera", None) is not None:
            if camera is not None and camera != renderer.camera:
                raise ConfigError("camera differs from the given renderer's camera; give one of them")
            camera = renderer.camera
        self.camera = camera if camera is not None else default_camera()
        self.camera_height_m = float(camera_height_m)
        self.seed = int(seed)
        if start_pose is None:
            if not world.routes:
                raise ConfigError("this world has no route to start from; give start_pose=(x, z, theta)")
            start_pose = route_start(world, "loop" if "loop" in world.route_names else world.route_names[0])
        pose = tuple(float(v) for v in start_pose)
        if len(pose) != 3 or not all(math.isfinite(v) for v in pose):
            raise ConfigError(f"start pose {start_pose!r} must be three finite numbers x, z, theta")
        if not world.is_free(pose[0], pose[1]):
            raise ConfigError(f"start pose ({pose[0]:.2f}, {pose[1]:.2f}) is inside a wall; pick a point on the free floor")
        self._vehicle = Vehicle(self.vehicle_config, self.disturbance_config, world.segments, pose, seed=self.seed)
        self.conditions = parse_conditions(conditions)
        c = self.conditions
        if not self._owns_renderer and (c.changes_light or c.changes_world):
            raise ConfigError("light and moved-panel conditions need a renderer the simulator creates; "
                              "give a renderer name, or build the renderer with those conditions")
        self._renderer = (
            make_renderer(renderer, moved_world(world, c), self.camera, self.camera_height_m,
                          **(c.renderer_options() if c.changes_light else {}))
            if isinstance(renderer, str) else renderer
        )
        self._camera_rng = np.random.default_rng([self.seed, c.seed, 16])
        self._trajectory: list[tuple[float, float, float, float]] = []
        self._log()
        self.robot = Robot(self)
        self.ground_truth = GroundTruth(self)

    def _image(self, pose: Pose) -> np.ndarray:
        img = np.array(self._renderer.render(pose), dtype=np.uint8, copy=True)
        return apply_conditions(img, self.conditions, self._camera_rng) if self.conditions.changes_image else img

    def _log(self) -> None:
        v = self._vehicle
        self._trajectory.append((v.time_s, float(v.pose[0]), float(v.pose[1]), float(v.pose[2])))

    def close(self) -> None:
        """Release the renderer if the simulator created it (a renderer passed in stays open)."""
        close = getattr(self._renderer, "close", None)
        if self._owns_renderer and close is not None:
            close()

    def __enter__(self) -> Simulator:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
