"""The built-in demonstration and episode recording: teach -> build -> navigate -> plots.

:func:`run_demo` is what ``topomap navigate`` does without arguments: generate the default world,
teach its loop, build the map, start near the first node and navigate to the node farthest along
the route, then write ``trajectory.png``, ``camera.gif``, the map and ``result.json``.

:class:`EpisodeRecorder` collects what an episode shows (camera images, events) for the plots and
the animation; it listens to the navigator's events and never feeds anything back.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from topomap.graph import TopoMap
from topomap.groundtruth import PoseTable, read_poses
from topomap.navigate import EventKind, NavEvent
from topomap.sim.episode import EpisodeResult, goal_pose, run_episode
from topomap.sim.world import World

__all__ = ["EpisodeRecorder", "DemoResult", "run_demo", "farthest_node", "plot_episode", "DEMO_DISTURBANCE"]

log = logging.getLogger(__name__)

#: The demo's unknown input disturbance: constant biases on every channel (THESIS.md section 1).
DEMO_DISTURBANCE = "bias"


@dataclass
class EpisodeRecorder:
    """Keeps every ``every``-th camera image (with the subgoal's thumbnail beside it) and all
    non-step events of a navigation, for :meth:`write_animation` and ``events.jsonl``."""

    tmap: TopoMap
    every: int = 4
    max_frames: int = 400
    frames: list[np.ndarray] = field(default_factory=list)
    events: list[dict] = field(default_factory=list)
    _steps: int = 0

    def __call__(self, ev: NavEvent) -> None:
        if ev.kind is not EventKind.STEP:
            self.events.append({"time_s": round(ev.time_s, 2), "kind": ev.kind.value, "message": ev.message,
                                "subgoal": ev.subgoal})
            return
        self._steps += 1
        if ev.image is not None and self._steps % self.every == 0 and len(self.frames) < self.max_frames:
            self.frames.append(self._panel(ev))

    def _panel(self, ev: NavEvent) -> np.ndarray:
        cam = ev.image if ev.image.ndim == 3 else cv2.cvtColor(ev.image, cv2.COLOR_GRAY2RGB)
        h, w = cam.shape[:2]
        thumb = self.tmap.nodes[ev.subgoal].thumbnail
        thumb = cv2.resize(thumb, (w // 2, int(round(thumb.shape[0] * (w / 2) / thumb.shape[1]))))
        side = np.full((h, w // 2, 3), 30, np.uint8)
        side[: min(h, thumb.shape[0]), :, :] = cv2.cvtColor(thumb[: h], cv2.COLOR_GRAY2RGB)
        panel = np.hstack([cam, side])
        s = ev.servo
        lines = [f"t {ev.time_s:5.1f} s  subgoal {ev.subgoal}", s.status.value if s else ""]
        if s is not None and math.isfinite(s.position_error_m):
            lines.append(f"est {s.position_error_m:.2f} m {math.degrees(s.heading_error_rad):+.1f} deg")
        for i, text in enumerate(lines):
            cv2.putText(panel, text, (w + 4, h - 40 + 14 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (255, 255, 0), 1, cv2.LINE_AA)
        return panel

    def write_animation(self, path: str | Path, fps: float = 8.0) -> Path | None:
        """An animated GIF of the recorded camera panels (``None`` when nothing was recorded)."""
        import imageio.v2 as imageio

        if not self.frames:
            return None
        path = Path(path)
        imageio.mimsave(path, [f[::2, ::2] for f in self.frames], duration=1.0 / fps, loop=0)
        return path

    def write_events(self, path: str | Path) -> Path:
        path = Path(path)
        path.write_text("".join(json.dumps(e) + "\n" for e in self.events))
        return path

    def write_all(self, folder: str | Path, world: World, poses: PoseTable, result: EpisodeResult, *,
                  title: str | None = None, data: dict | None = None) -> dict[str, Path]:
        """``trajectory.png``, ``camera.gif`` (when frames were kept), ``events.jsonl`` and
        ``result.json`` (``data``, default the whole result) in ``folder``; returns name -> path."""
        folder = Path(folder)
        files = {"trajectory": plot_episode(world, self.tmap, poses, result, folder / "trajectory.png", title=title)}
        anim = self.write_animation(folder / "camera.gif")
        if anim is not None:
            files["animation"] = anim
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
) -> DemoResult:
    """Default world -> teach run of its loop -> map -> navigate from near node 0 to ``goal``
    (default: the farthest node) -> ``trajectory.png``, ``camera.gif``, ``map.topomap``, ``result.json``."""
    from topomap.build import build_map
    from topomap.camera import load_camera
    from topomap.sim.teach import teach
    from topomap.sim.world import default_world
    from topomap.store import save_map

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

    def listen(ev: NavEvent) -> None:
        rec(ev)
        if on_event is not None:
            on_event(ev)

    result = run_episode(tmap, world, goal, poses, start_pose=start, vehicle=vehicle, disturbance=disturbance,
                         seed=seed, on_event=listen)
    title = (f"node {start_node} -> {goal}: {result.status}, "
             f"{result.final_position_error_m:.3f} m / {result.final_heading_error_deg:.1f} deg")
    files = {"map": map_path, **rec.write_all(out, world, poses, result, title=title)}
    return DemoResult(out, map_path, result, files)
