"""Rerun recordings of navigation runs and maps (the ``viz`` extra: ``rerun-sdk``, imported on use).

:class:`RerunLogger` listens to the navigator's events, like
:class:`~topomap.viz.animation.CameraAnimation`: it is not part of the control loop and feeds nothing
back. Per control step (timelines ``time``, robot seconds, and ``step``) it logs

============================  ================================================================
``camera/image``              the camera image (JPEG)
``camera/image/matches``      the features matched to the subgoal (green: kept by the servo's pose)
``camera/image/flow``         arrows from each kept feature's place in the keyframe to its place now
``subgoal/image``             the subgoal's keyframe (when the subgoal changes), ``.../matches``
``world/walls``               the floor plan (simulation; static)
``world/map/nodes|edges``     keyframe positions and edges by kind (static)
``world/route``, ``world/subgoal``  the current plan and subgoal
``world/estimate``            the servo's relative pose placed at the subgoal keyframe's position,
                              and its trail: what the robot believes
``world/truth``               the simulator's pose and trail (simulation only, for scoring)
``map/graph``                 the map as a graph (static)
``servo/*``, ``command/*``    distance [m], heading [deg], inliers, d_omega [rad/s], kappa; the command
``truth/*``                   true distance to the subgoal keyframe's pose [m] (simulation only)
``events``                    the navigator's events as a text log
============================  ================================================================

Floor-plan positions ``(x, z)`` are logged as ``(x, -z)`` so that z points up as in
``trajectory.png`` (Rerun's 2-D views point y down). Keyframe positions come from the teach run's
poses: a display aid that never reaches the navigator.

:func:`log_map` records a map alone: its graph, and each keyframe's thumbnail on a ``node`` timeline.
"""

from __future__ import annotations

import logging
import math
import os
import shutil
import sys
from collections.abc import Mapping
from pathlib import Path

import cv2
import numpy as np

from topomap.errors import ConfigError, MissingExtraError
from topomap.graph import EdgeKind, TopoMap
from topomap.viz.overlay import StepMatches, keyframe_image, step_matches

__all__ = ["RerunLogger", "log_map", "open_recording", "check_rerun", "can_spawn_viewer", "APPLICATION_ID"]

log = logging.getLogger(__name__)

APPLICATION_ID = "topomap"
#: Trails (cumulative line strips) are re-logged every this many steps: each copy holds the whole
#: trail, so logging it every step would grow the file with the square of the run's length.
TRAIL_EVERY = 5

_EDGE_RGB = {EdgeKind.SEQUENTIAL: (110, 110, 110), EdgeKind.LOOP: (220, 60, 60), EdgeKind.MANUAL: (60, 110, 220)}
_INLIER, _OUTLIER = (60, 220, 90), (235, 70, 60)
_LEVEL = {"arrived": "INFO", "failed": "ERROR", "timeout": "ERROR", "lost": "WARN", "replanned": "WARN"}


def _rr():
    try:
        import rerun as rr
    except ImportError:
        raise MissingExtraError("Rerun logging needs the rerun-sdk library: pip install 'appearance-topomap[viz]'") from None
    return rr


def can_spawn_viewer() -> str | None:
    """Why no Rerun viewer can be started here, or None when one can (a display and the viewer)."""
    if shutil.which("rerun") is None and not (Path(sys.executable).parent / "rerun").exists():
        return "the Rerun viewer (`rerun`) is not installed: pip install 'appearance-topomap[viz]'"
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        return "there is no display (DISPLAY / WAYLAND_DISPLAY unset); write a file with --rerun FILE.rrd and open it with `rerun FILE.rrd`"
    return None


def check_rerun(spawn: bool = False) -> None:
    """Raise the one-line error now if Rerun is not installed, or (``spawn``) no viewer can start."""
    _rr()
    why = can_spawn_viewer() if spawn else None
    if why is not None:
        raise ConfigError(f"cannot start a Rerun viewer: {why}")


def open_recording(path: str | Path | None = None, spawn: bool = False, name: str = "topomap", blueprint=None):
    """A Rerun recording stream writing to ``path`` (an ``.rrd`` file) and/or a spawned viewer."""
    rr = _rr()
    if path is None and not spawn:
        raise ConfigError("give a file to write (--rerun FILE.rrd) or --rerun-spawn")
    if path is not None and Path(path).suffix.lower() != ".rrd":
        raise ConfigError(f"cannot write {Path(path).name}: a Rerun recording's file name ends in .rrd")
    check_rerun(spawn)
    rec = rr.RecordingStream(APPLICATION_ID)
    rec.send_recording_name(name)
    sinks = []
    if path is not None:
        sinks.append(rr.FileSink(str(path)))
    if spawn:
        rr.spawn(connect=False, recording=rec)
        sinks.append(rr.GrpcSink())
    rec.set_sinks(*sinks, default_blueprint=blueprint)
    return rec


def _xy(x: float, z: float) -> list[float]:
    return [float(x), -float(z)]


def _jpeg(image: np.ndarray) -> bytes:
    bgr = image if image.ndim == 2 else cv2.cvtColor(image[:, :, :3], cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 80])  # a third smaller than 90 (docs/visualization.md)
    return buf.tobytes()


def _log_graph(rec, tmap: TopoMap, positions: Mapping[int, np.ndarray] | None) -> None:
    """``map/graph`` (and ``world/map/*`` when positions are given), static."""
    rr = _rr()
    ids = sorted(tmap.nodes)
    pos = None if positions is None else np.array([_xy(*positions[n][:2]) for n in ids], np.float32)
    rec.log("map/graph", rr.GraphNodes([str(n) for n in ids], labels=[str(n) for n in ids],
                                       positions=pos), static=True)
    rec.log("map/graph", rr.GraphEdges([(str(e.a), str(e.b)) for e in sorted(tmap.edges.values(), key=lambda e: e.key)],
                                       graph_type="undirected"), static=True)
    if pos is None:
        return
    index = {n: i for i, n in enumerate(ids)}
    rec.log("world/map/nodes", rr.Points2D(pos, radii=0.06, colors=(30, 30, 30), labels=[str(n) for n in ids],
                                           show_labels=False), static=True)
    for kind in EdgeKind:
        strips = [[pos[index[e.a]], pos[index[e.b]]] for e in tmap.edges.values() if e.kind is kind]
        if strips:
            rec.log(f"world/map/edges/{kind.value}", rr.LineStrips2D(strips, radii=0.02, colors=_EDGE_RGB[kind]), static=True)


def _blueprint(run: bool):
    import rerun.blueprint as rrb

    if not run:
        return rrb.Blueprint(rrb.Horizontal(rrb.GraphView(origin="map/graph", name="map graph"),
                                            rrb.Vertical(rrb.Spatial2DView(origin="map/keyframe", name="keyframe"),
                                                         rrb.Spatial2DView(origin="world", name="keyframe positions"))))
    return rrb.Blueprint(rrb.Horizontal(
        rrb.Vertical(rrb.Spatial2DView(origin="camera", name="camera"), rrb.Spatial2DView(origin="subgoal", name="subgoal keyframe")),
        rrb.Vertical(rrb.Spatial2DView(origin="world", name="floor plan"), rrb.TextLogView(origin="events", name="events")),
        rrb.Vertical(rrb.TimeSeriesView(origin="servo", name="servo estimates"), rrb.TimeSeriesView(origin="command", name="command"),
                     rrb.TimeSeriesView(origin="truth", name="ground truth (scoring)")),
    ))


class RerunLogger:
    """Navigator event listener that logs a run to Rerun (see the module docstring for the layout).

    ``tmap``: the map being navigated; ``path``: the ``.rrd`` file to write and/or ``spawn`` a viewer;
    ``node_poses``: node id -> ``(x, z, theta)`` where its keyframe was taken (the teach run's poses),
    to draw the map, the route and the estimated pose over the floor plan (without them only the
    images, graph, scalars and events are logged). Call :meth:`close` at the end.
    """

    def __init__(self, tmap: TopoMap, path: str | Path | None = None, *, spawn: bool = False,
                 node_poses: Mapping[int, tuple[float, float, float]] | None = None, name: str = "navigation"):
        self.rr = _rr()
        self.tmap = tmap
        self.path = Path(path) if path is not None else None
        self.rec = open_recording(path, spawn, name, _blueprint(run=True))
        self.node_poses = {int(k): np.asarray(v, float) for k, v in node_poses.items()} if node_poses else None
        self.steps = 0
        self._subgoal: int | None = None
        self._route: tuple[int, ...] = ()
        self._estimate: list[list[float]] = []
        self._truth: list[list[float]] = []
        self._time = 0.0
        _log_graph(self.rec, tmap, self.node_poses)

    # -- world (simulation)
    def log_world(self, world) -> None:
        """The floor plan of a simulator world (static)."""
        seg = np.asarray(world.segments, float).reshape(-1, 2, 2)
        strips = [[_xy(*a), _xy(*b)] for a, b in seg]
        self.rec.log("world/walls", self.rr.LineStrips2D(strips, radii=0.03, colors=(60, 90, 160)), static=True)

    def log_truth(self, time_s: float, pose) -> None:
        """The simulator's true pose ``(x, z, theta)`` at ``time_s`` (scoring only)."""
        rr = self.rr
        x, z, th = (float(v) for v in pose[:3])
        self._at(time_s)
        self.rec.log("world/truth", rr.Points2D([_xy(x, z)], radii=0.1, colors=(40, 120, 230)))
        self.rec.log("world/truth/heading", rr.Arrows2D(origins=[_xy(x, z)], vectors=[[0.5 * math.cos(th), -0.5 * math.sin(th)]],
                                                        colors=(40, 120, 230)))
        self._truth.append(_xy(x, z))
        if len(self._truth) % TRAIL_EVERY == 1:
            self.rec.log("world/truth/trail", rr.LineStrips2D([self._truth], radii=0.03, colors=(40, 120, 230)))
        if self.node_poses is not None and self._subgoal in self.node_poses:
            g = self.node_poses[self._subgoal]
            self.rec.log("truth/distance_to_subgoal_m", rr.Scalars(float(math.hypot(x - g[0], z - g[1]))))

    # -- events
    def _at(self, time_s: float) -> None:
        self._time = float(time_s)
        self.rec.set_time("time", duration=self._time)
        self.rec.set_time("step", sequence=self.steps)

    def __call__(self, ev) -> None:
        from topomap.navigate import EventKind

        self._at(ev.time_s)
        if ev.route and tuple(ev.route) != self._route:
            self._route = tuple(ev.route)
            if self.node_poses is not None:
                pts = [_xy(*self.node_poses[n][:2]) for n in self._route if n in self.node_poses]
                self.rec.log("world/route", self.rr.LineStrips2D([pts], radii=0.05, colors=(60, 180, 75)))
        if ev.subgoal is not None and ev.subgoal != self._subgoal and ev.subgoal in self.tmap.nodes:
            self._log_subgoal(int(ev.subgoal))
        if ev.kind is EventKind.STEP:
            self._log_step(ev)
            self.steps += 1
        else:
            self.rec.log("events", self.rr.TextLog(f"{ev.kind.value}: {ev.message}", level=_LEVEL.get(ev.kind.value, "INFO")))

    def _log_subgoal(self, node: int) -> None:
        rr = self.rr
        self._subgoal = node
        key = keyframe_image(self.tmap, node)
        self.rec.log("subgoal/image", rr.EncodedImage(contents=_jpeg(key), media_type="image/jpeg"))
        if self.node_poses is not None and node in self.node_poses:
            g = self.node_poses[node]
            self.rec.log("world/subgoal", rr.Points2D([_xy(g[0], g[1])], radii=0.15, colors=(250, 160, 30),
                                                      labels=[f"subgoal {node}"]))

    def _log_step(self, ev) -> None:
        rr, rec = self.rr, self.rec
        image = ev.image
        if image is not None:
            rec.log("camera/image", rr.EncodedImage(contents=_jpeg(image), media_type="image/jpeg"))
            m = step_matches(self.tmap, ev) if ev.subgoal is not None else None
            if m is not None:
                self._log_matches(m, image.shape[1::-1], keyframe_image(self.tmap, ev.subgoal).shape[1::-1])
        s = ev.servo
        if s is not None:
            rec.log("servo/inliers", rr.Scalars(float(s.inliers)))
            if math.isfinite(s.position_error_m):
                rec.log("servo/distance_m", rr.Scalars(float(s.position_error_m)))
            if math.isfinite(s.heading_error_rad):
                rec.log("servo/heading_deg", rr.Scalars(math.degrees(s.heading_error_rad)))
            d = s.disturbance
            rec.log("servo/d_omega_rps", rr.Scalars(float(d.d_omega)))
            if math.isfinite(d.kappa):
                rec.log("servo/kappa", rr.Scalars(float(d.kappa)))
            self._log_estimate(s, ev.subgoal)
        c = ev.command
        if c is not None:
            rec.log("command/v_f_mps", rr.Scalars(float(c.v_f)))
            rec.log("command/v_h_mps", rr.Scalars(float(c.v_h)))
            rec.log("command/omega_rps", rr.Scalars(float(c.omega)))

    def _log_matches(self, m: StepMatches, cam_size, key_size) -> None:
        rr = self.rr
        if not len(m):
            self.rec.log("camera/image/matches", rr.Clear(recursive=False))
            self.rec.log("camera/image/flow", rr.Clear(recursive=False))
            self.rec.log("subgoal/image/matches", rr.Clear(recursive=False))
            return
        cur = m.cur_px * (cam_size[0] / m.size[0], cam_size[1] / m.size[1])
        goal_on_cam = m.goal_px * (cam_size[0] / m.size[0], cam_size[1] / m.size[1])
        goal = m.goal_px * (key_size[0] / m.size[0], key_size[1] / m.size[1])
        colors = np.where(m.inlier[:, None], _INLIER, _OUTLIER).astype(np.uint8)
        self.rec.log("camera/image/matches", rr.Points2D(cur, radii=2.0, colors=colors))
        self.rec.log("camera/image/flow", rr.Arrows2D(origins=goal_on_cam[m.inlier], vectors=(cur - goal_on_cam)[m.inlier],
                                                      colors=_INLIER, radii=0.7))
        self.rec.log("subgoal/image/matches", rr.Points2D(goal, radii=2.0 * key_size[0] / cam_size[0], colors=colors))

    def _log_estimate(self, s, subgoal: int | None) -> None:
        """The servo's pose relative to the subgoal, placed at the subgoal keyframe's teach pose."""
        if self.node_poses is None or subgoal not in self.node_poses or not math.isfinite(s.heading_error_rad):
            return
        pose = s.pose
        if math.isfinite(pose.x_s) and math.isfinite(pose.z_s) and s.position_error_s > 0:
            scale = s.position_error_m / s.position_error_s  # metres per scaled unit at this subgoal
            fwd, left = pose.x_s * scale, pose.z_s * scale
        elif s.position_error_s == 0:
            fwd = left = 0.0  # the images show no translation: at the keyframe's position
        else:
            return
        gx, gz, gth = self.node_poses[subgoal]
        x = gx + math.cos(gth) * fwd - math.sin(gth) * left
        z = gz + math.sin(gth) * fwd + math.cos(gth) * left
        th = gth + s.heading_error_rad
        rr = self.rr
        self.rec.log("world/estimate", rr.Points2D([_xy(x, z)], radii=0.1, colors=(230, 80, 200)))
        self.rec.log("world/estimate/heading", rr.Arrows2D(origins=[_xy(x, z)], vectors=[[0.5 * math.cos(th), -0.5 * math.sin(th)]],
                                                           colors=(230, 80, 200)))
        self._estimate.append(_xy(x, z))
        if len(self._estimate) % TRAIL_EVERY == 1:
            self.rec.log("world/estimate/trail", rr.LineStrips2D([self._estimate], radii=0.03, colors=(230, 80, 200)))

    def close(self) -> Path | None:
        """Log the trails' final state, flush and close; returns the ``.rrd`` path (if any)."""
        rr = self.rr
        for entity, trail, colour in (("world/truth/trail", self._truth, (40, 120, 230)),
                                      ("world/estimate/trail", self._estimate, (230, 80, 200))):
            if trail:
                self.rec.log(entity, rr.LineStrips2D([trail], radii=0.03, colors=colour))
        _finish(self.rec, self.path)
        return self.path


def _finish(rec, path: Path | None) -> None:
    """Flush and close a recording. A viewer that went away (closed, or failed to start: no usable
    GPU) fails the flush of its sink; the run and the file are not lost for that."""
    try:
        rec.flush()
    except RuntimeError as e:
        log.warning("the Rerun viewer stopped receiving (%s)%s", str(e).splitlines()[0][:120],
                    f"; {path} holds the whole recording" if path is not None else "")
    rec.disconnect()


def log_map(tmap: TopoMap, path: str | Path | None = None, *, spawn: bool = False,
            positions: Mapping[int, np.ndarray] | None = None) -> Path | None:
    """Record a map: its graph (``map/graph``; ``world/map/*`` at ``positions``, node id -> (x, z)),
    and each keyframe's thumbnail (``map/keyframe``) on the ``node`` timeline. Returns ``path``."""
    rr = _rr()
    rec = open_recording(path, spawn, "map", _blueprint(run=False))
    _log_graph(rec, tmap, positions)
    for n in sorted(tmap.nodes):
        rec.set_time("node", sequence=n)
        rec.log("map/keyframe", rr.EncodedImage(contents=_jpeg(tmap.nodes[n].thumbnail), media_type="image/jpeg"))
        if positions is not None:
            rec.log("world/map/selected", rr.Points2D([_xy(*positions[n][:2])], radii=0.15, colors=(250, 160, 30),
                                                      labels=[f"node {n}: {tmap.nodes[n].source}"]))
    _finish(rec, Path(path) if path is not None else None)
    return Path(path) if path is not None else None
