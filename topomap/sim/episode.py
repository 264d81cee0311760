"""Navigation episodes in simulation, scored with ground truth.

This module stands on both sides of the boundary on purpose, and is the only place that does: it
hands the navigator ``sim.robot`` (images and commands only) and keeps ``sim.ground_truth`` to
itself, to place the robot at the start and to score the end. The scorer compares the final pose
with the pose where the goal node's keyframe was taken in the teach run (``poses.csv``).

:func:`replay_episode` is the *blind replay* baseline: the teach run's commands, from the start
node's image to the goal node's image, played back open loop (dead reckoning) under the same
disturbances.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from topomap.config import LocalizeConfig, NavigateConfig, ServoConfig
from topomap.errors import DatasetError
from topomap.graph import TopoMap
from topomap.groundtruth import PoseTable
from topomap.localize import Localizer
from topomap.motion import Command, wrap_angle
from topomap.navigate import EventKind, NavEvent, Navigator, NavStatus
from topomap.sim.conditions import Conditions
from topomap.sim.simulator import Simulator
from topomap.sim.world import World

__all__ = ["SUCCESS_POSITION_M", "SUCCESS_HEADING_DEG", "EpisodeResult", "goal_pose", "run_episode",
           "replay_episode", "read_commands"]

#: An episode succeeds when it ends within these of the goal node's pose.
SUCCESS_POSITION_M = 0.25
SUCCESS_HEADING_DEG = 10.0


@dataclass
class EpisodeResult:
    """Outcome of one episode. Errors and lengths come from the simulator's ground truth."""

    success: bool
    status: str
    final_position_error_m: float
    final_heading_error_deg: float
    path_length_m: float
    teach_path_length_m: float
    duration_s: float
    subgoals_reached: int
    replans: int
    goal: int
    start_node: int | None
    message: str = ""
    collisions: int = 0
    trajectory: np.ndarray = field(default=None, repr=False)  # (T, 3) x, z, theta

    def to_dict(self) -> dict:
        d = asdict(self)
        d.pop("trajectory")
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in d.items()}


def goal_pose(tmap: TopoMap, poses: PoseTable, node: int) -> np.ndarray:
    """Ground-truth pose ``(x, z, theta)`` where the node's keyframe was taken."""
    src = tmap.node(node).source
    if src not in poses:
        raise DatasetError(f"the poses file has no pose for keyframe {src} of node {node}; is it the map's teach run?")
    return np.asarray(poses[src], float)


def _route_length(tmap: TopoMap, poses: PoseTable, nodes) -> float:
    pts = [goal_pose(tmap, poses, n)[:2] for n in nodes]
    return float(sum(np.linalg.norm(b - a) for a, b in zip(pts, pts[1:])))


def _score(sim: Simulator, target: np.ndarray) -> tuple[float, float, np.ndarray, float]:
    p = np.array(sim.ground_truth.pose(), float)
    traj = np.asarray(sim.ground_truth.trajectory(), float)[:, 1:4]  # columns t, x, z, theta -> x, z, theta
    err = float(np.hypot(p[0] - target[0], p[1] - target[1]))
    herr = math.degrees(abs(wrap_angle(p[2] - target[2])))
    length = float(np.linalg.norm(np.diff(traj[:, :2], axis=0), axis=1).sum()) if len(traj) > 1 else 0.0
    return err, herr, traj, length


def run_episode(
    tmap: TopoMap,
    world: World,
    goal: int,
    poses: PoseTable,
    *,
    start_pose: tuple[float, float, float] | None = None,
    start_node: int | None = None,
    vehicle: str = "unicycle",
    disturbance: str = "none",
    seed: int = 0,
    servo_config: ServoConfig | None = None,
    navigate_config: NavigateConfig | None = None,
    localize_config: LocalizeConfig | None = None,
    localizer: Localizer | None = None,
    on_event: Callable[[NavEvent], None] | None = None,
    on_truth: Callable[[float, np.ndarray], None] | None = None,
    conditions: str | Conditions | None = None,
    keyframe_image: Callable[[int], np.ndarray | None] | None = None,
) -> EpisodeResult:
    """Put a simulated robot at ``start_pose`` (default: the keyframe pose of ``start_node``, or of
    node 0), let the navigator drive it to ``goal`` from images alone, and score the end.

    ``on_event`` hears the navigator's events; ``on_truth(time_s, pose)`` the simulator's true pose
    ``(x, z, theta)`` where each control step's image was taken (for recordings and scoring only);
    ``conditions``: how the repeat run looks (:mod:`topomap.sim.conditions`; default as taught);
    ``keyframe_image``: a node's keyframe image where ``tmap`` holds none (e.g.
    :func:`topomap.store.load_node_image` of its file), for the near floor's arrival check."""
    target = goal_pose(tmap, poses, goal)
    if start_pose is None:
        start_pose = tuple(goal_pose(tmap, poses, start_node if start_node is not None else min(tmap.nodes)))
    with Simulator(world, vehicle=vehicle, disturbance=disturbance, seed=seed, start_pose=start_pose,
                   camera=_camera_for(tmap), conditions=conditions) as sim:
        nav = Navigator(tmap, sim.robot, vehicle, navigate_config, servo_config, localize_config, localizer=localizer,
                        keyframe_image=keyframe_image)
        first_route: tuple[int, ...] = ()
        for ev in nav.run(goal, start_node=start_node):
            if ev.kind is EventKind.PLANNED and not first_route:
                first_route = ev.route
            if on_event is not None:
                on_event(ev)
            if on_truth is not None and ev.kind is EventKind.STEP:
                on_truth(ev.time_s, np.array(sim.ground_truth.pose(), float))  # the robot has not moved since the image
        out = nav.outcome
        err, herr, traj, length = _score(sim, target)
        collisions = sim.ground_truth.collisions
    arrived = out.status is NavStatus.ARRIVED
    success = arrived and err <= SUCCESS_POSITION_M and herr <= SUCCESS_HEADING_DEG
    return EpisodeResult(
        success=success, status=out.status.value, final_position_error_m=err, final_heading_error_deg=herr,
        path_length_m=length, teach_path_length_m=_route_length(tmap, poses, first_route) if first_route else 0.0,
        duration_s=out.duration_s, subgoals_reached=out.subgoals_reached, replans=out.replans, goal=int(goal),
        start_node=out.start_node, message=out.message, collisions=collisions, trajectory=traj,
    )


def _camera_for(tmap: TopoMap):
    """The simulated camera: the intrinsics the map was taught with, at the teach image size."""
    from topomap.sim.simulator import default_camera

    src = (tmap.sequences[0].get("input_size") if tmap.sequences else None) or [320, 240]
    w, h = int(src[0]), int(src[1])
    cam = tmap.camera.fitted_to(w, h)
    return cam if cam.source == "simulator" else default_camera(w, h)


def read_commands(teach_dir: str | Path) -> np.ndarray:
    """The teach run's commands: (K, 6) ``t_s, dt_s, v_f, v_h, omega, after_image``."""
    path = Path(teach_dir) / "commands.csv"
    if not path.is_file():
        raise DatasetError(f"{path} does not exist: blind replay needs a teach run that logged its commands")
    with open(path, newline="") as f:
        rows = [[float(r[k]) for k in ("t_s", "dt_s", "v_f", "v_h", "omega", "after_image")] for r in csv.DictReader(f)]
    return np.array(rows)


def replay_episode(
    tmap: TopoMap,
    world: World,
    goal: int,
    poses: PoseTable,
    commands: np.ndarray,
    start_node: int,
    *,
    vehicle: str = "unicycle",
    disturbance: str = "none",
    seed: int = 0,
) -> EpisodeResult:
    """Blind replay: start exactly at ``start_node``'s keyframe pose and play the teach commands
    recorded between that image and the goal's image (wrapping around a loop route), open loop."""
    names = [f.source for f in tmap.frames if f.sequence == 0]
    index = {n: i for i, n in enumerate(names)}
    a, b = index[tmap.node(start_node).source], index[tmap.node(goal).source]
    after = commands[:, 5].astype(int)
    if a <= b:
        sel = (after >= a) & (after < b)
        cmds = commands[sel]
    else:  # around the loop: to the end of the run, then from its start
        cmds = np.concatenate([commands[after >= a], commands[after < b]])
    target = goal_pose(tmap, poses, goal)
    start = tuple(goal_pose(tmap, poses, start_node))
    with Simulator(world, vehicle=vehicle, disturbance=disturbance, seed=seed, start_pose=start,
                   camera=_camera_for(tmap)) as sim:
        for t, dt, vf, vh, om, _ in cmds:
            sim.robot.apply(Command(vf, vh, om), dt)
        err, herr, traj, length = _score(sim, target)
        duration = sim.ground_truth.time_s()
        collisions = sim.ground_truth.collisions
    success = err <= SUCCESS_POSITION_M and herr <= SUCCESS_HEADING_DEG
    teach_len = float(np.linalg.norm(np.diff(np.array([poses[n][:2] for n in names]), axis=0), axis=1)[
        min(a, b):max(a, b)].sum()) if a != b else 0.0
    return EpisodeResult(success, "replayed", err, herr, length, teach_len, duration, 0, 0, int(goal), int(start_node),
                         collisions=collisions, trajectory=traj)
