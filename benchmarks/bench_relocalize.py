"""Re-localization after a loss: the navigator's whole search from lost poses, two rules on the same poses.

A lost robot stands near the node that last verified well, at any heading: up to 1.2 m from a random
keyframe, turned up to 90 deg from its view, ``harsh`` disturbances. ``Navigator._relocalize`` then
searches by turning in place, as after a loss in an episode (the last good node is that keyframe's),
once with each rule on the same pose:

* ``localizer`` — the localizer's answer among the near nodes (``recover_scale_tolerance=None``);
* ``scale`` — of the near nodes that verify, one showing the scene at the frame's scale
  (``NavigateConfig.recover_scale_tolerance``, the default).

The ground truth only scores: the answered keyframe's distance from the robot where it stopped, wrong
when more than 1.5 m or 60 deg off (``bench_navigate_unseen.py``'s wrong-localization bound). Worlds
and photograph sets are ``bench_navigate_unseen.py``'s (held-out seeds there; quote the seeds a
figure comes from, and which were looked at while choosing a rule).

Run: ``python benchmarks/bench_relocalize.py [--worlds 165-174] [--per-world 12] [--conditions none]
[--cache DIR]`` (~1 s of CPU per search and rule, plus a teach run and map per world).
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_navigate_unseen as unseen  # noqa: E402  (worlds, photograph sets, caches)

RULES = {"localizer": None, "scale": "default"}
WRONG_M, WRONG_DEG = 1.5, 60.0


def lost_poses(world, kp: dict, n: int, rng: np.random.Generator) -> list[tuple[int, tuple[float, float, float]]]:
    """``n`` (last good node, pose) pairs: up to 1.2 m from the node's keyframe, up to 90 deg off its view."""
    ids, out = sorted(kp), []
    while len(out) < n:
        s = int(rng.choice(ids))
        x, z, th = kp[s]
        d, a = rng.uniform(0.0, 1.2), rng.uniform(-math.pi, math.pi)
        pose = (x + d * math.cos(a), z + d * math.sin(a), th + rng.uniform(-math.pi / 2, math.pi / 2))
        if world.is_free(pose[0], pose[1]) and world.clearance(pose[0], pose[1]) >= 0.3:
            out.append((s, pose))
    return out


def search(m, world, loc, camera, last: int, pose, seed: int, conditions, tolerance) -> tuple[int, float, np.ndarray]:
    """One re-localization from ``pose`` with ``last`` as the last good node: (answered node, robot time [s],
    true pose where it stopped, for scoring)."""
    from topomap.config import NavigateConfig
    from topomap.navigate import Navigator
    from topomap.sim.simulator import Simulator

    cfg = NavigateConfig() if tolerance == "default" else NavigateConfig(recover_scale_tolerance=tolerance)
    with Simulator(world, vehicle="unicycle", disturbance="harsh", seed=seed, start_pose=pose, camera=camera,
                   conditions=conditions) as sim:
        nav = Navigator(m, sim.robot, "unicycle", cfg, localizer=loc)
        nav._last_good = nav._here = last
        for _ in nav._relocalize():
            pass
        return nav._here, nav._time, np.array(sim.ground_truth.pose(), float)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--worlds", default="165-174", help="world seeds (bench_navigate_unseen.py's worlds)")
    ap.add_argument("--per-world", type=int, default=12, help="lost poses per world")
    ap.add_argument("--conditions", default=None, help="repeat-run conditions (as bench_navigate_unseen.py)")
    ap.add_argument("--seed", type=int, default=13)
    ap.add_argument("--cache", type=Path, default=None, help="texture sets, teach runs and maps (reused)")
    args = ap.parse_args(argv)

    from topomap.groundtruth import read_poses
    from topomap.localize import Localizer
    from topomap.sim.episode import _camera_for
    from topomap.sim.world import load_world
    from topomap.store import load_map

    seeds = unseen.parse_worlds(args.worlds)
    cache = args.cache or Path(tempfile.mkdtemp(prefix="bench_relocalize_"))
    results: dict[str, list[tuple[float, bool, float]]] = {r: [] for r in RULES}
    changed = better = 0
    for k, seed in enumerate(seeds):
        spec = unseen.world_spec(seed, k, "default")
        if spec["textures"]:
            unseen.texture_folder(spec["textures"], cache)
        path = unseen.prepare(spec, cache, None)
        m, teach = load_map(path), path.parent / "teach"
        poses, world = read_poses(teach / "poses.csv"), load_world(teach / "world.json")
        loc, camera = Localizer(m), _camera_for(m)
        kp = {n: np.array(poses[m.nodes[n].source], float) for n in m.nodes}
        rng = np.random.default_rng([seed, args.seed])
        for i, (last, pose) in enumerate(lost_poses(world, kp, args.per_world, rng)):
            got = {}
            for rule, tol in RULES.items():
                node, t, truth = search(m, world, loc, camera, last, pose, seed * 1000 + i, args.conditions, tol)
                d = float(math.hypot(kp[node][0] - truth[0], kp[node][1] - truth[1]))
                dth = math.degrees(abs(math.remainder(kp[node][2] - truth[2], 2 * math.pi)))
                results[rule].append((d, d > WRONG_M or dth > WRONG_DEG, t))
                got[rule] = (node, d)
            if got["localizer"][0] != got["scale"][0]:
                changed += 1
                better += got["scale"][1] < got["localizer"][1]
        print(f"world {seed} done ({spec['textures']})", file=sys.stderr, flush=True)

    n = len(results["scale"])
    print(f"\nre-localization from {n} lost poses, worlds {args.worlds}, conditions {args.conditions or 'nominal'}, "
          "harsh disturbances (distance of the answered keyframe from the robot, by the ground truth)")
    print(f"{'rule':<11}{'wrong':>7}{'median m':>10}{'p90 m':>8}{'> 3 m':>7}{'robot s':>9}")
    for rule, rows in results.items():
        d = np.array([r[0] for r in rows])
        print(f"{rule:<11}{sum(r[1] for r in rows):7d}{np.median(d):10.2f}{np.percentile(d, 90):8.2f}"
              f"{int(np.sum(d > 3.0)):7d}{np.mean([r[2] for r in rows]):9.1f}")
    print(f"the rules answered differently on {changed} poses; the scale rule nearer on {better}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
