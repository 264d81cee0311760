"""The built-in demonstration and episode recording: teach -> build -> navigate -> plots.

:func:`run_demo` is what ``topomap navigate`` does without arguments: generate the default world,
teach its loop, build the map, start near the first node and navigate to the node farthest along
the route, then write ``trajectory.png``, ``camera.gif`` (and ``camera.mp4``), the map and
``result.json``.

:class:`EpisodeRecorder` collects what an episode shows (camera images, events) for the plots and
the animation; it listens to the navigator's events and never feeds anything back.
"""

from __future__ import annotations

import functools
import json
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from topomap.graph import TopoMap
from topomap.groundtruth import PoseTable, read_poses
from topomap.navigate import EventKind, NavEvent
from topomap.sim.episode import EpisodeResult, goal_pose, run_episode
from topomap.sim.world import World
from topomap.viz.animation import CameraAnimation

__all__ = ["EpisodeRecorder", "DemoResult", "run_demo", "farthest_node", "plot_episode", "DEMO_DISTURBANCE"]

log = logging.getLogger(__name__)

#: The demo's unknown input disturbance: constant biases on every channel (docs/theory.md §1.2).
DEMO_DISTURBANCE = "bias"


@dataclass
class EpisodeRecorder:
    """Records a navigation for its files: the camera animation (every ``every``-th control step,
    :class:`~topomap.viz.animation.CameraAnimation`) and all non-step events."""

    tmap: TopoMap
    every: int = 2
    max_shots: int = 9000
    events: list[dict] = field(default_factory=list)
    animation: CameraAnimation = field(init=False)

    def __post_init__(self) -> None:
        self.animation = CameraAnimation(self.tmap, self.every, self.max_shots)

    def __call__(self, ev: NavEvent) -> None:
        if ev.kind is not EventKind.STEP:
            self.events.append({"time_s": round(ev.time_s, 2), "kind": ev.kind.value, "message": ev.message,
                                "subgoal": ev.subgoal})
        self.animation(ev)

    def write_animation(self, path: str | Path) -> Path | None:
        """The animated GIF (``None`` when nothing was recorded)."""
        return self.animation.write_gif(path)

    def write_events(self, path: str | Path) -> Path:
        path = Path(path)
        path.write_text("".join(json.dumps(e) + "\n" for e in self.events))
        return path

    def write_all(self, folder: str | Path, world: World, poses: PoseTable, result: EpisodeResult, *,
                  title: str | None = None, data: dict | None = None) -> dict[str, Path]:
        """``trajectory.png``, ``camera.gif`` and ``camera.mp4`` (when frames were kept; the MP4 when
        imageio's ffmpeg plugin is installed), ``events.jsonl`` and ``result.json`` (``data``,
        default the whole result) in ``folder``; returns name -> path."""
        folder = Path(folder)
        files = {"trajectory": plot_episode(world, self.tmap, poses, result, folder / "trajectory.png", title=title)}
        anim = self.write_animation(folder / "camera.gif")
        if anim is not None:
            files["animation"] = anim
        video = self.animation.write_mp4(folder / "camera.mp4")
        if video is not None:
            files["video"] = video
        files["events"] = self.write_events(folder / "events.jsonl")
        files["result"] = folder / "result.json"
        files["result"].write_text(json.dumps(result.to_dict() if data is None else data, indent=2) + "\n")
        return files


def plot_episode(world: World, tmap: TopoMap, poses: PoseTable, result: EpisodeResult, path: str | Path,
                 teach_route: str | None = "loop", title: str | None = None) -> Path:
    """Floor plan with the teach path, the driven path, the map's nodes, start and goal."""
    from topomap.sim.plot import plot_world

    nodes = np.array([goal_pose(tmap, poses, n)[:2] for n in sorted(tmap.nodes)])
    teach = np.array([poses[n][:2] for n in poses.names])
    fig = plot_world(world, None, route=None, trajectories={"teach run": teach, "driven": result.trajectory[:, :2]},
                     title=title)
    ax = fig.axes[0]
    ax.scatter(nodes[:, 0], nodes[:, 1], s=10, c="k", zorder=5, label="map nodes")
    g = goal_pose(tmap, poses, result.goal)
    st = result.trajectory[0]
    ax.plot(*st[:2], "o", ms=9, mfc="none", mec="tab:green", mew=2, zorder=6, label="start")
    ax.plot(*g[:2], "*", ms=14, c="tab:red", zorder=6, label=f"goal (node {result.goal})")
    ax.legend(loc="upper right", fontsize=7)
    path = Path(path)
    fig.savefig(path)
    return path


def farthest_node(tmap: TopoMap, start: int) -> int:
    """The reachable node with the most expensive route from ``start`` (ties: the higher id)."""
    from topomap.plan import Planner

    costs = Planner(tmap).costs_from(start)
    costs.pop(start)
    return max(costs, key=lambda n: (costs[n], n))


@dataclass
class DemoResult:
    out_dir: Path
    map_path: Path
    result: EpisodeResult
    files: dict[str, Path]


def run_demo(
    out_dir: str | Path = "topomap-demo",
    *,
    vehicle: str = "unicycle",
    disturbance: str = DEMO_DISTURBANCE,
    seed: int = 0,
    goal: int | None = None,
    on_stage: Callable[[str], None] | None = None,
    on_event: Callable[[NavEvent], None] | None = None,
    rerun: str | Path | None = None,
    rerun_spawn: bool = False,
) -> DemoResult:
    """Default world -> teach run of its loop -> map -> navigate from near node 0 to ``goal``
    (default: the farthest node) -> ``trajectory.png``, ``camera.gif`` (``camera.mp4`` with the viz
    extra), ``map.topomap``, ``result.json``; ``rerun``: also a Rerun recording of the run (an
    ``.rrd`` file), ``rerun_spawn``: streamed to a viewer (:class:`~topomap.viz.rerun.RerunLogger`)."""
    from topomap.build import build_map
    from topomap.camera import load_camera
    from topomap.sim.teach import teach
    from topomap.sim.world import default_world
    from topomap.store import load_node_image, save_map

    def stage(msg: str) -> None:
        log.info(msg)
        if on_stage is not None:
            on_stage(msg)

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    world = default_world()
    stage("teaching the default world's loop")
    run = teach(world, "loop", out / "teach", overwrite=True)
    stage(f"building the map from {run.frames} images")
    tmap = build_map(out / "teach", camera=load_camera(run.camera_path))
    map_path = save_map(tmap, out / "map.topomap", overwrite=True)
    poses = read_poses(run.poses_path)
    start_node = min(tmap.nodes)
    goal = farthest_node(tmap, start_node) if goal is None else goal
    tmap.node(goal)
    # start a little off the first node: 15 cm to the side, turned by 10 degrees
    x, z, th = goal_pose(tmap, poses, start_node)
    start = (x - 0.15 * math.sin(th), z + 0.15 * math.cos(th), th + math.radians(10))
    stage(f"navigating from near node {start_node} to node {goal} ({vehicle}, disturbance {disturbance})")
    rec = EpisodeRecorder(tmap)
    viewer = None
    if rerun is not None or rerun_spawn:
        from topomap.viz.rerun import RerunLogger

        viewer = RerunLogger(tmap, rerun, spawn=rerun_spawn, node_poses={n: goal_pose(tmap, poses, n) for n in tmap.nodes},
                             name="demo")
        viewer.log_world(world)

    def listen(ev: NavEvent) -> None:
        rec(ev)
        if viewer is not None:
            viewer(ev)
        if on_event is not None:
            on_event(ev)

    result = run_episode(tmap, world, goal, poses, start_pose=start, vehicle=vehicle, disturbance=disturbance,
                         seed=seed, on_event=listen, on_truth=viewer.log_truth if viewer is not None else None,
                         keyframe_image=functools.partial(load_node_image, map_path))
    title = (f"node {start_node} -> {goal}: {result.status}, "
             f"{result.final_position_error_m:.3f} m / {result.final_heading_error_deg:.1f} deg")
    files = {"map": map_path, **rec.write_all(out, world, poses, result, title=title)}
    if viewer is not None and viewer.close() is not None:
        files["rerun"] = Path(rerun)
    return DemoResult(out, map_path, result, files)
