"""The simulator: textured indoor worlds, a camera-carrying vehicle with unknown input disturbances (docs/theory.md section 1).

* :mod:`~topomap.sim.world` — floor plans (corridors, junctions, rooms, loops) from a seed, JSON files;
* :mod:`~topomap.sim.textures` — wall photographs and procedural patterns;
* :mod:`~topomap.sim.conditions` — changed conditions between teach and repeat (light, camera, moved panels);
* :mod:`~topomap.sim.render` — the :class:`Renderer` protocol and its PyBullet (TinyRenderer) backend;
* :mod:`~topomap.sim.vehicle` — unicycle / omni kinematics ``xi' = G(theta)(u + d)``, disturbance presets, collisions;
* :mod:`~topomap.sim.simulator` — :class:`Simulator` with its two sides, ``sim.robot`` (images and
  commands: all navigation may use) and ``sim.ground_truth`` (poses: scoring and teaching only);
* :mod:`~topomap.sim.teach` — the ground-truth driver that records teach runs;
* :mod:`~topomap.sim.plot` — floor-plan drawings.
"""

from __future__ import annotations

from topomap.sim.conditions import CONDITION_PRESETS, Conditions, apply_conditions, moved_world, parse_conditions
from topomap.sim.geometry import CAMERA_HEIGHT_M, Pose, camera_from_world, project_world_points
from topomap.sim.plot import plot_world
from topomap.sim.render import RENDERERS, PyBulletRenderer, Renderer, make_renderer
from topomap.sim.simulator import GroundTruth, Robot, RobotInterface, Simulator, StepReport, default_camera, route_start
from topomap.sim.teach import PurePursuit, TeachConfig, TeachResult, teach
from topomap.sim.vehicle import (
    DISTURBANCE_PRESETS,
    DisturbanceConfig,
    VehicleConfig,
    arc_step,
    disturbance_preset,
    parse_disturbance,
)
from topomap.sim.world import (
    WORLD_STYLES,
    Marker,
    Rect,
    WaypointRoute,
    Wall,
    World,
    default_world,
    generate_world,
    load_world,
    office_world,
    resolve_world,
)

__all__ = [
    "World", "Wall", "Rect", "WaypointRoute", "Marker", "generate_world", "default_world", "load_world", "resolve_world",
    "Renderer", "PyBulletRenderer", "RENDERERS", "make_renderer",
    "Pose", "CAMERA_HEIGHT_M", "camera_from_world", "project_world_points",
    "DisturbanceConfig", "DISTURBANCE_PRESETS", "disturbance_preset", "parse_disturbance", "VehicleConfig", "arc_step",
    "Simulator", "Robot", "RobotInterface", "GroundTruth", "StepReport", "default_camera", "route_start",
    "teach", "TeachConfig", "TeachResult", "PurePursuit",
    "plot_world",
    "Conditions", "CONDITION_PRESETS", "parse_conditions", "apply_conditions", "moved_world",
    "WORLD_STYLES", "office_world",
]
