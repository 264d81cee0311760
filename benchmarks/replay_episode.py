"""Replay one episode of ``bench_navigate.py`` with its events and, for diagnosis, the ground truth.

The benchmark's success rates hide *how* an episode fails; this prints the navigator's events
(localized, planned, subgoal switches, lost, re-planned, arrived) and, while servoing toward the
final goal, the servo's estimate beside the true distance and heading error every ``--every``
seconds. The ground truth is read from the simulator for printing only; the navigator never sees it.

The episode is drawn exactly as the benchmark draws it (same ``--episodes``, ``--worlds``,
``--seed``, ``--textures``), so ``world 1 ep 12`` here is ``world 1 ep 12`` of the benchmark's log.

Run: ``python benchmarks/replay_episode.py --world 1 --episode 12 [--worlds 0,1] [--episodes 40]
[--textures DIR] [--method topomap|uncompensated] [--cache DIR]``.

An episode of ``bench_navigate_unseen.py`` is replayed from that run's log, which records each
episode whole (map, start, goal, seeds, conditions): ``--run LOG --world 103 --episode 4``.
"""

from __future__ import annotations

import argparse
import functools
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_navigate as bench  # noqa: E402  (the benchmark's episode drawing and caches)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--world", type=int, required=True, help="world seed of the episode")
    ap.add_argument("--episode", type=int, required=True, help="its index within that world")
    ap.add_argument("--worlds", default="0,1", help="the benchmark run's worlds (as bench_navigate.py)")
    ap.add_argument("--episodes", type=int, default=40, help="the benchmark run's episode count")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--textures", default=None)
    ap.add_argument("--disturbance", default="harsh")
    ap.add_argument("--method", choices=("topomap", "uncompensated"), default="topomap")
    ap.add_argument("--budget-per-hop", type=float, default=10.0)
    ap.add_argument("--every", type=float, default=1.0, help="print a goal step every this many seconds")
    ap.add_argument("--cache", type=Path, default=None, help="teach runs and maps (bench_navigate.py --cache)")
    ap.add_argument("--run", type=Path, default=None,
                    help="a bench_navigate_unseen.py log (.jsonl) or --json file: replay its episode as recorded")
    ap.add_argument("--conditions", default=None,
                    help="repeat-run conditions instead of the recorded ones (e.g. none: the same episode as taught)")
    args = ap.parse_args(argv)

    from topomap.config import NavigateConfig, servo_preset
    from topomap.navigate import EventKind
    from topomap.sim import simulator
    from topomap.sim.episode import goal_pose, run_episode
    from topomap.store import load_node_image

    conditions = None
    if args.run is not None:
        ep, map_path, conditions, args.disturbance, args.budget_per_hop = _from_run(ap, args)
    else:
        seeds = [int(s) for s in args.worlds.split(",")]
        if args.world not in seeds:
            ap.error(f"--world {args.world} is not one of --worlds {args.worlds}")
        cache = args.cache or Path(tempfile.mkdtemp(prefix="bench_navigate_"))
        maps = [bench.prepare_world(s, cache, args.textures) for s in seeds]
        rng = np.random.default_rng(args.seed)
        per = [args.episodes // len(seeds) + (i < args.episodes % len(seeds)) for i in range(len(seeds))]
        drawn = [bench.draw_episodes(p, s, n, rng, 0.4, 10, 1000 * s) for s, p, n in zip(seeds, maps, per)]
        k = seeds.index(args.world)
        if not 0 <= args.episode < len(drawn[k]):
            ap.error(f"world {args.world} has episodes 0..{len(drawn[k]) - 1}")
        ep, map_path = drawn[k][args.episode], maps[k]
    if args.conditions is not None:
        conditions = args.conditions
    m, world, poses, _, loc = bench._load(str(map_path))
    print(f"world {ep.world} ep {ep.index}: {ep.vehicle}, start node {ep.start_node} at {np.round(ep.start_pose, 3)}, "
          f"goal {ep.goal}, disturbance seed {ep.seed}" + (f", conditions {conditions}" if conditions else ""))

    sims: list = []  # the simulator, captured to print the truth beside the estimates
    enter = simulator.Simulator.__enter__

    def capture(self):
        sims.append(self)
        return enter(self)

    simulator.Simulator.__enter__ = capture
    gx, gz, gth = goal_pose(m, poses, ep.goal)
    last = [-math.inf]

    def on_event(ev) -> None:
        if ev.kind is not EventKind.STEP:
            truth = ""
            if ev.kind is EventKind.LOCALIZED and sims:  # where the robot truly was, and the nearest keyframe
                x, z, th = (float(v) for v in sims[-1]._vehicle.pose)
                lx, lz, lth = goal_pose(m, poses, ev.subgoal)
                near = min(m.nodes, key=lambda n: math.dist(goal_pose(m, poses, n)[:2], (x, z)))
                truth = (f"  | truly {math.hypot(lx - x, lz - z):.2f} m and "
                         f"{abs(math.degrees(math.remainder(lth - th, 2 * math.pi))):.0f} deg from it; nearest node {near}")
            print(f"{ev.time_s:7.1f} s  {ev.kind.value:<10} {ev.message}{truth}")
            return
        if ev.subgoal != ep.goal or ev.time_s - last[0] < args.every - 1e-9:
            return
        last[0] = ev.time_s
        x, z, th = (float(v) for v in sims[-1]._vehicle.pose)
        s = ev.servo
        hdg = math.degrees(s.heading_error_rad) if math.isfinite(s.heading_error_rad) else math.nan
        true_hdg = math.degrees(math.remainder(th - gth, 2 * math.pi))
        print(f"{ev.time_s:7.1f} s    goal {s.status.value:<11} estimate {s.position_error_m:6.3f} m {hdg:6.1f} deg"
              f" | true {math.hypot(x - gx, z - gz):6.3f} m {true_hdg:6.1f} deg | {s.inliers} inliers,"
              f" command v {ev.command.v_f:+.3f} omega {ev.command.omega:+.3f}")

    r = run_episode(m, world, ep.goal, poses, start_pose=ep.start_pose, vehicle=ep.vehicle,
                    disturbance=args.disturbance, seed=ep.seed, localizer=loc,
                    servo_config=servo_preset("default" if args.method == "topomap" else "uncompensated"),
                    navigate_config=NavigateConfig(time_budget_s_per_hop=args.budget_per_hop), on_event=on_event,
                    conditions=conditions, keyframe_image=functools.partial(load_node_image, map_path))
    print(r.to_dict())
    return 0 if r.success else 1


def _from_run(ap, args):
    """(episode, map path, conditions, disturbance, budget per hop) of ``--world``/``--episode`` in a run's log."""
    import json

    if not args.run.is_file():
        ap.error(f"--run {args.run} does not exist")
    text = args.run.read_text()
    try:
        rows = json.loads(text)["episodes"] if args.run.suffix == ".json" else [json.loads(x) for x in text.splitlines() if x.strip()]
    except (ValueError, KeyError, TypeError):
        ap.error(f"--run {args.run} is not a bench_navigate_unseen.py log or --json file")
    job = next((r["job"] for r in rows if r.get("world") == args.world and r.get("episode") == args.episode
                and "job" in r), None)
    if job is None:
        ap.error(f"--run {args.run} has no episode {args.episode} of world {args.world}")
    e = job["episode"]
    ep = bench.Episode(e["world"], e["index"], e["vehicle"], e["start_node"], e["goal"], tuple(e["start_pose"]), e["seed"])
    return ep, Path(job["map"]), job.get("conditions"), job["disturbance"], job["budget_per_hop"]


if __name__ == "__main__":
    from topomap.errors import TopomapError

    try:
        sys.exit(main())
    except TopomapError as e:  # bad input (e.g. --textures): one line, no traceback
        sys.exit(f"Error: {e}")
