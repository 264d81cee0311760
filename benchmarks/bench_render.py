"""Benchmark: rendered frames per second of the default world at 320x240 and 640x480.

Poses: every 0.5 m along the default world's ``loop`` route, heading along the route with a
+-0.3 rad sway (what a teach or navigation run sees). Rows:

* ``topomap`` — :class:`topomap.sim.render.PyBulletRenderer` as the simulator uses it (tessellated
  panels, exact visibility culling);
* ``no culling`` — the same scene with every panel drawn (ablation);
* ``naive scene`` — one quad per panel and per floor/ceiling tile, no culling: what a direct PyBullet
  scene would cost;
* ``empty scene`` — the baseline: TinyRenderer's ``getCameraImage`` on an empty scene at the same
  size, i.e. the fixed per-frame cost (buffers, copies) no scene content can go below.

The ratio column is each row's frame time over the empty scene's, measured in the same run. Goal:
at least 50 frames/s at 320x240. Run: ``python benchmarks/bench_render.py`` (about 20 s).
"""

from __future__ import annotations

import math
import sys
import time

import numpy as np

from topomap.sim.render import PyBulletRenderer, _import_pybullet, gl_projection, gl_view
from topomap.sim.simulator import default_camera
from topomap.sim.world import default_world

SIZES = [(320, 240), (640, 480)]
GOAL_FPS = 50.0


def loop_poses(world, step_m: float = 0.5) -> list[tuple[float, float, float]]:
    p = world.route("loop").points
    poses = []
    for a, b in zip(p[:-1], p[1:]):
        length = float(np.linalg.norm(b - a))
        heading = math.atan2(b[1] - a[1], b[0] - a[0])
        for s in np.arange(0.0, length, step_m):
            q = a + (b - a) * s / length
            poses.append((float(q[0]), float(q[1]), heading + 0.3 * math.sin(len(poses))))
    return poses


def time_frames(render, poses, repeat: int = 2) -> tuple[float, float]:
    """Mean (wall-clock, CPU) seconds per frame after 3 warm-up frames.

    The machine is shared: wall-clock time includes waiting for a core, the process's CPU time does
    not, so both are reported.
    """
    for pose in poses[:3]:
        render(pose)
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(repeat):
        for pose in poses:
            render(pose)
    n = repeat * len(poses)
    return (time.perf_counter() - t0) / n, (time.process_time() - c0) / n


def empty_scene(camera):
    p = _import_pybullet()
    cid = p.connect(p.DIRECT)
    proj = gl_projection(camera, 0.05, 100.0).T.flatten().tolist()

    def render(pose):
        view = gl_view(pose, 0.8).T.flatten().tolist()
        p.getCameraImage(camera.width, camera.height, view, proj, renderer=p.ER_TINY_RENDERER,
                         flags=p.ER_NO_SEGMENTATION_MASK, shadow=0, physicsClientId=cid)

    return render, lambda: p.disconnect(physicsClientId=cid)


def main() -> int:
    world = default_world()
    poses = loop_poses(world)
    print(f"default world: {len(world.walls)} wall panels, {len(world.free)} floor tiles; {len(poses)} poses along 'loop'")
    results: dict[str, dict[tuple[int, int], tuple[float, float]]] = {}
    for size in SIZES:
        cam = default_camera(*size)
        render, close = empty_scene(cam)
        results.setdefault("empty scene (baseline)", {})[size] = time_frames(render, poses)
        close()
        for label, options in [
            ("topomap", {}),
            ("no culling", {"cull": False}),
            ("naive scene", {"cull": False, "cell_m": 1e6}),
        ]:
            with PyBulletRenderer(world, cam, **options) as r:
                results.setdefault(label, {})[size] = time_frames(r.render, poses)
    base = results["empty scene (baseline)"]
    print("ms = wall-clock per frame (cpu = the process's CPU time); fps from wall-clock; ratio = cpu time / empty scene's")
    head = "".join(f" | {w}x{h}: ms (cpu) |  fps | ratio" for w, h in SIZES)
    print(f"{'renderer':<24}{head}")
    for label in ("topomap", "no culling", "naive scene", "empty scene (baseline)"):
        row = ""
        for s in SIZES:
            wall, cpu = results[label][s]
            row += f" | {1e3 * wall:7.1f} ({1e3 * cpu:5.1f}) | {1.0 / wall:4.0f} | {cpu / base[s][1]:5.1f}"
        print(f"{label:<24}{row}")
    wall, cpu = results["topomap"][SIZES[0]]
    verdict = "met" if 1.0 / wall >= GOAL_FPS else "NOT met (wall clock)"
    print(f"goal >= {GOAL_FPS:.0f} frames/s at 320x240: {1.0 / wall:.0f} frames/s wall-clock, "
          f"{1.0 / cpu:.0f} per CPU-second: {verdict}")
    try:
        import os

        print(f"load average during the run: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    except (AttributeError, OSError):  # pragma: no cover - platform without getloadavg
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
