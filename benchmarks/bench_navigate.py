"""Navigation in simulation: topomap vs the uncompensated servo vs blind replay, same episodes.

For each world (the default world and generated worlds of other seeds) the benchmark teaches the
world's loop, builds the map, and draws episodes: a random start node, a start pose up to
``--start-offset`` metres and 17 degrees off its keyframe pose, a random goal node at most
``--max-hops`` route hops away (default 10, about 5 m of corridor: it keeps the 40 x 3 runs near half
an hour on 2 cores; 0 allows any goal), a vehicle (unicycle and omni alternate), and a seed of
the ``--disturbance`` preset (default ``harsh``). Every episode is run three ways, side by side:

* **topomap**: the navigator (localize -> plan -> servo -> switch) with the default servo, which
  estimates and cancels the unknown input disturbances (docs/theory.md sections 2-3);
* **uncompensated**: the same navigator and servo laws with disturbance compensation off
  (``servo_preset("uncompensated")``);
* **blind replay**: the teach run's own commands from the start node's image to the goal's image,
  replayed open loop (dead reckoning) under the same disturbance, starting exactly at the start
  node's keyframe pose (a head start the other two do not get).

Success: within 0.25 m and 10 degrees of the goal keyframe's pose (ground truth, used only to
score). Prints success rate, median / 90th-percentile position error, median heading error per
method and per vehicle, and the ratio of each baseline's median error to topomap's.

Both navigators get 60 s + ``--budget-per-hop`` (10 s; topomap needs about 4) per route hop.

Run: ``python benchmarks/bench_navigate.py [--episodes 40] [--worlds 0,1] [--jobs 2] [--json out.json]``.
Teach runs and maps are cached in ``--cache`` (default: a temporary folder).
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

METHODS = ("topomap", "uncompensated", "blind replay")


@dataclass(frozen=True)
class Episode:
    world: int
    index: int
    vehicle: str
    start_node: int
    goal: int
    start_pose: tuple[float, float, float]
    seed: int


def prepare_world(seed: int, cache: Path, textures: str | None = None) -> Path:
    """Teach the loop of world ``seed`` (wall photographs from ``textures`` if given) and build its
    map (cached); returns the map path."""
    from topomap.build import build_map
    from topomap.camera import load_camera
    from topomap.sim.teach import teach
    from topomap.sim.world import WORLD_VERSION, default_world, generate_world
    from topomap.store import save_map

    # the world format in the name: a cache of worlds the generator made before is not taken for today's
    folder = cache / (f"world{seed}" + (f"-{Path(textures).name}" if textures else "") + f"-w{WORLD_VERSION}")
    map_path = folder / "map.topomap"
    if map_path.is_file():
        return map_path
    world = default_world() if seed == 0 and not textures else generate_world(seed, textures=textures)
    run = teach(world, "loop", folder / "teach", overwrite=True)
    tmap = build_map(folder / "teach", camera=load_camera(run.camera_path))
    return save_map(tmap, map_path, overwrite=True)


def draw_episodes(map_path: Path, world_seed: int, n: int, rng: np.random.Generator, start_offset: float,
                  max_hops: int | None, disturbance_seed0: int) -> list[Episode]:
    from topomap.groundtruth import read_poses
    from topomap.plan import Planner
    from topomap.sim.world import load_world
    from topomap.store import load_map

    m = load_map(map_path)
    teach = map_path.parent / "teach"
    poses, world = read_poses(teach / "poses.csv"), load_world(teach / "world.json")
    planner = Planner(m)
    ids = sorted(m.nodes)
    out = []
    while len(out) < n:
        s, g = (int(v) for v in rng.choice(ids, 2, replace=False))
        if max_hops and planner.route(s, g).hops > max_hops:
            continue
        x, z, th = poses[m.nodes[s].source]
        d, a = rng.uniform(0.0, start_offset), rng.uniform(-math.pi, math.pi)
        pose = (x + d * math.cos(a), z + d * math.sin(a), th + rng.uniform(-0.3, 0.3))
        if not world.is_free(pose[0], pose[1]) or world.clearance(pose[0], pose[1]) < 0.3:
            continue
        k = len(out)
        out.append(Episode(world_seed, k, ("unicycle", "omni")[k % 2], s, g, pose, disturbance_seed0 + k))
    return out


_CACHE: dict = {}


def _load(map_path: str):
    if map_path not in _CACHE:
        from topomap.groundtruth import read_poses
        from topomap.localize import Localizer
        from topomap.sim.episode import read_commands
        from topomap.sim.world import load_world
        from topomap.store import load_map

        m = load_map(map_path)
        teach = Path(map_path).parent / "teach"
        _CACHE[map_path] = (m, load_world(teach / "world.json"), read_poses(teach / "poses.csv"),
                            read_commands(teach), Localizer(m))
    return _CACHE[map_path]


def run_one(args: tuple[str, Episode, str, str, float]) -> dict:
    """One episode, one method (in a worker process)."""
    map_path, ep, method, disturbance, budget = args
    from topomap.config import NavigateConfig, servo_preset
    from topomap.sim.episode import replay_episode, run_episode
    from topomap.store import load_node_image

    m, world, poses, commands, loc = _load(map_path)
    t0 = time.perf_counter()
    if method == "blind replay":
        r = replay_episode(m, world, ep.goal, poses, commands, ep.start_node, vehicle=ep.vehicle,
                           disturbance=disturbance, seed=ep.seed)
    else:
        servo = servo_preset("default" if method == "topomap" else "uncompensated")
        r = run_episode(m, world, ep.goal, poses, start_pose=ep.start_pose, vehicle=ep.vehicle,
                        disturbance=disturbance, seed=ep.seed, servo_config=servo, localizer=loc,
                        navigate_config=NavigateConfig(time_budget_s_per_hop=budget),
                        keyframe_image=functools.partial(load_node_image, map_path))
    return {"world": ep.world, "episode": ep.index, "vehicle": ep.vehicle, "method": method,
            "start_node": ep.start_node, "goal": ep.goal, **r.to_dict(), "wall_s": round(time.perf_counter() - t0, 2)}


def summarize(rows: list[dict]) -> dict:
    def stats(sel: list[dict]) -> dict:
        err = np.array([r["final_position_error_m"] for r in sel])
        herr = np.array([r["final_heading_error_deg"] for r in sel])
        return {"episodes": len(sel), "success_rate": float(np.mean([r["success"] for r in sel])),
                "median_error_m": float(np.median(err)), "p90_error_m": float(np.percentile(err, 90)),
                "median_heading_error_deg": float(np.median(herr)),
                "median_wall_s": float(np.median([r["wall_s"] for r in sel]))}

    out = {}
    for method in METHODS:
        sel = [r for r in rows if r["method"] == method]
        if not sel:
            continue
        out[method] = {"all": stats(sel)}
        for v in ("unicycle", "omni"):
            vs = [r for r in sel if r["vehicle"] == v]
            if vs:
                out[method][v] = stats(vs)
    base = out["topomap"]["all"]["median_error_m"]
    for method in METHODS[1:]:
        if method in out:
            out[method]["all"]["error_ratio_vs_topomap"] = out[method]["all"]["median_error_m"] / max(base, 1e-9)
    return out


def print_table(summary: dict, wall_s: float) -> None:
    print(f"\n{'method':<14} {'vehicle':<9} {'n':>3} {'success':>8} {'median err':>11} {'p90 err':>9} "
          f"{'median hdg':>11} {'ratio':>7} {'wall/ep':>8}")
    for method, by in summary.items():
        for v, s in by.items():
            ratio = s.get("error_ratio_vs_topomap")
            print(f"{method:<14} {v:<9} {s['episodes']:>3} {s['success_rate']:>8.1%} {s['median_error_m']:>9.3f} m "
                  f"{s['p90_error_m']:>7.3f} m {s['median_heading_error_deg']:>7.1f} deg "
                  f"{(f'{ratio:.1f}x' if ratio is not None else ''):>7} {s['median_wall_s']:>6.1f} s")
    print(f"(ratio: the method's median position error / topomap's; total wall time {wall_s / 60:.1f} min)")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=40, help="episodes in all, split over the worlds")
    ap.add_argument("--worlds", default="0,1", help="world seeds (0 = the default world)")
    ap.add_argument("--disturbance", default="harsh")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--start-offset", type=float, default=0.4, help="start up to this far from the start keyframe [m]")
    ap.add_argument("--max-hops", type=int, default=10, help="only goals at most this many route hops away (0: any)")
    ap.add_argument("--budget-per-hop", type=float, default=10.0,
                    help="navigation time budget: 60 s + this per route hop [s] (both servos)")
    ap.add_argument("--textures", default=None,
                    help="photograph folder for the walls of generated worlds (unseen textures; default: the built-in crops)")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cache", type=Path, default=None, help="folder for teach runs and maps (reused)")
    ap.add_argument("--json", type=Path, default=None, help="write every episode and the summary here")
    args = ap.parse_args(argv)
    methods = [m.strip() for m in args.methods.split(",")]
    if unknown := set(methods) - set(METHODS):
        ap.error(f"unknown methods {sorted(unknown)}; choose from {', '.join(METHODS)}")
    seeds = [int(s) for s in args.worlds.split(",")]
    cache = args.cache or Path(tempfile.mkdtemp(prefix="bench_navigate_"))
    cache.mkdir(parents=True, exist_ok=True)

    t0 = time.perf_counter()
    rng = np.random.default_rng(args.seed)
    jobs: list[tuple[str, Episode, str, str, float]] = []
    with ProcessPoolExecutor(args.jobs) as pool:
        maps = list(pool.map(prepare_world, seeds, [cache] * len(seeds), [args.textures] * len(seeds)))
        print(f"worlds {seeds}: maps ready in {time.perf_counter() - t0:.0f} s ({cache})", flush=True)
        per = [args.episodes // len(seeds) + (i < args.episodes % len(seeds)) for i in range(len(seeds))]
        drawn = [draw_episodes(path, seed, n, rng, args.start_offset, args.max_hops, 1000 * seed)
                 for seed, path, n in zip(seeds, maps, per)]
        for k in range(max(per)):  # worlds interleaved: a partial run still covers every world
            for path, eps in zip(maps, drawn):
                if k < len(eps):
                    jobs += [(str(path), eps[k], method, args.disturbance, args.budget_per_hop) for method in methods]
        rows = []
        for row in pool.map(run_one, jobs):
            rows.append(row)
            print(f"world {row['world']} ep {row['episode']:>2} {row['vehicle']:<8} {row['method']:<13} "
                  f"{row['start_node'] if row['start_node'] is not None else '?':>3} -> {row['goal']:<3} {row['status']:<8} "
                  f"{'ok  ' if row['success'] else 'FAIL'} {row['final_position_error_m']:.3f} m "
                  f"{row['final_heading_error_deg']:5.1f} deg  {row['wall_s']:.0f} s", flush=True)
    wall = time.perf_counter() - t0
    summary = summarize(rows) if "topomap" in methods else {}
    if summary:
        print_table(summary, wall)
    if args.json is not None:
        args.json.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, "summary": summary,
                                         "episodes": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    from topomap.errors import TopomapError

    try:
        sys.exit(main())
    except TopomapError as e:  # bad input (e.g. --textures): one line, no traceback
        sys.exit(f"Error: {e}")
