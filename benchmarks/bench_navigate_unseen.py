"""Navigation on held-out worlds: tuning and testing kept apart, failures counted by kind.

``bench_navigate.py`` measures on the worlds the navigator was tuned on (seeds 0-5, the shipped
castle crops and the corridor ``query/`` frames as wall photographs). This benchmark reports on
data that tuning never looked at:

* **worlds**: seeds 100-129 are held out (default: 100-109, ten worlds); never tune on them —
  tune on 0-99 and quote figures from here (a held-out episode once diagnosed, as world 115 ep 0,
  is tuning data from then on: docs/navigation.md lists them; 120-129 were first run on 2026-12-03);
* **wall photographs**: three held-out sets, one per world in turn (:data:`TEXTURE_SETS`):
  ``corridor-ref`` (the corridor dataset's ``ref/`` traversal, real 160x120 frames),
  ``nordland`` (mosaics of 4 x 4 Nordland summer/winter frames, colour-tinted) and
  ``corridor-variants`` (``ref/`` frames cropped, hue-rotated, contrast-changed and paired); the
  tuning sets (``datasets/textures`` castle crops, corridor ``query/``) and the castle-P30 images
  they were cut from are never used here;
* **episodes**: goals anywhere in the map (``--max-hops 0``), starts up to 0.4 m and 17 deg off a
  random node, ``harsh`` disturbances, unicycle and omni alternating; each run by topomap, by the
  uncompensated servo and by blind replay (as ``bench_navigate.py``), in the same run;
* **conditions** (``--conditions``, :mod:`topomap.sim.conditions`): the repeat run under changed
  lighting, moved panels, evening or a noisy camera; ``--style office`` for the plain office.

Prints success with its 95 % Wilson interval, median / p90 final error, per vehicle, and the
failures counted by kind, derived from the navigator's events and outcome: ``wrong start
localization`` (the first localization was more than 1.5 m or 60 deg from the true start; the
ground truth only scores), ``no localization``, ``gave up (lost)`` / ``gave up (fooled)`` /
``gave up (blocked)`` / ``gave up (stuck)`` (recovery given up; the last loss: a subgoal out of sight / a look-alike at the goal /
the bumper in contact / a subgoal not reached in time), ``timeout``, ``false arrival`` (the navigator said arrived,
more than 0.25 m or 10 deg off). For a give-up it also reports how much of the time budget was left.

Run: ``python benchmarks/bench_navigate_unseen.py [--episodes 100] [--worlds 100-109] [--jobs 2]
[--conditions lighting] [--style office] [--methods topomap] [--cache DIR] [--json run.json]``.
Rows are appended to ``--log`` (default: ``run.jsonl`` beside ``--json``, or in the cache) as they
finish; ``--summarize LOG`` prints the table of a partial or finished log. Replay one episode with
``python benchmarks/replay_episode.py --run LOG --world 103 --episode 4``.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, fields, replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_navigate as bench  # noqa: E402  (episode drawing, the per-process map cache)

from topomap.config import NavigateConfig, preset_with_overrides, servo_preset  # noqa: E402
from topomap.errors import ConfigError  # noqa: E402
from topomap.store import load_node_image  # noqa: E402

METHODS = bench.METHODS
#: World seeds used for tuning so far; this benchmark refuses them unless --allow-tuning-worlds.
TUNING_WORLDS = range(0, 100)
HELD_OUT_WORLDS = range(100, 130)
#: Held-out wall photograph sets, assigned to the worlds in turn.
TEXTURE_SETS = ("corridor-ref", "nordland", "corridor-variants")
SHARED = Path(__file__).resolve().parents[1] / ".." / "shared" / "datasets"
WRONG_START_M = 1.5
WRONG_START_DEG = 60.0


# ---------------------------------------------------------------------- held-out photographs
def texture_folder(name: str, cache: Path) -> Path:
    """The folder of held-out texture set ``name`` (made once in ``cache/textures``, seeded)."""
    import cv2

    ref = SHARED / "corridor" / "ref"
    if name == "corridor-ref":
        return _existing(ref)
    out = cache / "textures" / name
    if (out / "DONE").is_file():
        return out
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng([16, TEXTURE_SETS.index(name)])
    if name == "nordland":
        frames = sorted(_existing(SHARED / "nordland-64x32" / "summer").glob("*.png"))
        frames += sorted(_existing(SHARED / "nordland-64x32" / "winter").glob("*.png"))
        for k in range(60):
            pick = rng.choice(len(frames), 16, replace=False)
            tiles = [cv2.imread(str(frames[i]), cv2.IMREAD_GRAYSCALE) for i in pick]
            rows = [np.hstack(tiles[r * 4:(r + 1) * 4]) for r in range(4)]
            grey = cv2.resize(np.vstack(rows), (512, 256), interpolation=cv2.INTER_CUBIC)
            tint = rng.uniform(0.55, 1.0, 3)
            img = np.clip(grey[:, :, None] * tint[None, None, :] + rng.uniform(0, 50, 3), 0, 255).astype(np.uint8)
            cv2.imwrite(str(out / f"nordland_{k:03d}.png"), img)
    elif name == "corridor-variants":
        frames = sorted(_existing(ref).glob("*.jpg"))
        for k in range(60):
            a, b = (cv2.imread(str(frames[i])) for i in rng.choice(len(frames), 2, replace=False))
            parts = []
            for img in (a, b):
                h, w = img.shape[:2]
                f = rng.uniform(0.7, 1.0)
                y0, x0 = int(rng.integers(0, h - int(f * h) + 1)), int(rng.integers(0, w - int(f * w) + 1))
                crop = cv2.resize(img[y0:y0 + int(f * h), x0:x0 + int(f * w)], (160, 120))
                hsv = cv2.cvtColor(crop, cv2.COLOR_BGR2HSV).astype(np.int32)
                hsv[..., 0] = (hsv[..., 0] + int(rng.integers(0, 180))) % 180
                hsv[..., 1] = np.clip(hsv[..., 1] * rng.uniform(1.0, 2.5) + 30, 0, 255)
                crop = cv2.cvtColor(hsv.astype(np.uint8), cv2.COLOR_HSV2BGR)
                parts.append(np.clip(crop * rng.uniform(0.8, 1.3) + rng.uniform(-30, 30), 0, 255).astype(np.uint8))
            cv2.imwrite(str(out / f"variant_{k:03d}.png"), np.hstack(parts))
    else:
        raise SystemExit(f"Error: unknown texture set {name!r}; choose from {', '.join(TEXTURE_SETS)}")
    (out / "DONE").write_text("ok\n")
    return out


def _existing(path: Path) -> Path:
    if not path.is_dir():
        raise SystemExit(f"Error: {path} is missing; the held-out photographs come from ../shared/datasets")
    return path


# ---------------------------------------------------------------------- worlds and episodes
def world_spec(seed: int, k: int, style: str) -> dict:
    """World ``seed`` (k-th of the run): its style and held-out texture set (office walls are plain)."""
    return {"seed": seed, "style": style, "textures": None if style == "office" else TEXTURE_SETS[k % len(TEXTURE_SETS)]}


def prepare(spec: dict, cache: Path, teach_conditions: str | None) -> Path:
    """Teach the loop of the world ``spec`` (under ``teach_conditions``) and build its map (cached)."""
    from topomap.build import build_map
    from topomap.camera import load_camera
    from topomap.sim.teach import teach
    from topomap.sim.world import WORLD_VERSION, generate_world
    from topomap.store import save_map

    tex = texture_folder(spec["textures"], cache) if spec["textures"] else None
    # the world format in the name: a cache of worlds the generator made before is not taken for today's
    tag = f"world{spec['seed']}-{spec['style']}-{spec['textures'] or 'plain'}-{teach_conditions or 'none'}-w{WORLD_VERSION}"
    folder = cache / tag
    map_path = folder / "map.topomap"
    if map_path.is_file():
        return map_path
    world = generate_world(spec["seed"], textures=tex, style=spec["style"])
    run = teach(world, "loop", folder / "teach", overwrite=True, conditions=teach_conditions)
    tmap = build_map(folder / "teach", camera=load_camera(run.camera_path))
    return save_map(tmap, map_path, overwrite=True)


def run_one(job: dict) -> dict:
    """One episode, one method (in a worker process); keeps the navigator's non-step events."""
    from topomap.config import NavigateConfig, servo_preset
    from topomap.navigate import EventKind
    from topomap.sim.episode import goal_pose, replay_episode, run_episode

    from topomap.sim import simulator

    ep = job["episode"]
    m, world, poses, commands, loc = bench._load(job["map"])
    events: list[dict] = []
    sims: list = []  # the episode's simulator: its ground truth scores each localization (never fed back)
    enter = simulator.Simulator.__enter__

    def capture(self):
        sims.append(self)
        return enter(self)

    def on_event(ev) -> None:
        if ev.kind is EventKind.STEP:
            return
        e = {"t": round(ev.time_s, 2), "kind": ev.kind.value, "message": ev.message,
             "node": ev.subgoal, "hops": max(0, len(ev.route) - 1) if ev.route else None}
        if ev.kind is EventKind.LOCALIZED and sims and ev.subgoal is not None:
            x, z, th = sims[-1].ground_truth.pose()
            lx, lz, lth = goal_pose(m, poses, ev.subgoal)
            e["error_m"] = round(math.hypot(lx - x, lz - z), 3)
            e["error_deg"] = round(abs(math.degrees(math.remainder(lth - th, 2 * math.pi))), 1)
        events.append(e)

    simulator.Simulator.__enter__ = capture
    t0 = time.perf_counter()
    try:
        if job["method"] == "blind replay":
            r = replay_episode(m, world, ep["goal"], poses, commands, ep["start_node"], vehicle=ep["vehicle"],
                               disturbance=job["disturbance"], seed=ep["seed"])
        else:
            servo = config_overrides(servo_preset("default" if job["method"] == "topomap" else "uncompensated"),
                                    job.get("servo"))
            r = run_episode(m, world, ep["goal"], poses, start_pose=tuple(ep["start_pose"]), vehicle=ep["vehicle"],
                            disturbance=job["disturbance"], seed=ep["seed"], servo_config=servo, localizer=loc,
                            navigate_config=config_overrides(NavigateConfig(time_budget_s_per_hop=job["budget_per_hop"]),
                                                            job.get("navigate"), "--navigate"),
                            on_event=on_event, conditions=job["conditions"],
                            keyframe_image=functools.partial(load_node_image, job["map"]))
    finally:
        simulator.Simulator.__enter__ = enter
    row = {"world": ep["world"], "episode": ep["index"], "vehicle": ep["vehicle"], "method": job["method"],
           "start_node": ep["start_node"], "goal": ep["goal"], **r.to_dict(),
           "wall_s": round(time.perf_counter() - t0, 2), "events": events, "job": job}
    if job["method"] != "blind replay":
        located = [e for e in events if e["kind"] == "localized" and "error_m" in e]
        if located:  # where the robot truly was when it localized (it may have turned to scan)
            row["start_localization_error_m"] = located[0]["error_m"]
            row["start_localization_error_deg"] = located[0]["error_deg"]
        row["wrong_relocalizations"] = sum(e["error_m"] > WRONG_START_M or e["error_deg"] > WRONG_START_DEG
                                           for e in located[1:])
        row["budget_s"] = round(_budget(events, job["budget_per_hop"]), 1)
    row["kind"], row["terminal_kind"] = failure_kind(row)
    return row


def _budget(events: list[dict], per_hop: float) -> float:
    """The navigator's time budget at the end, from its events: ``time_budget_base_s`` + per_hop per hop of the first
    route, extended at each of the first ``max_replans`` re-plans to the new route's (as :mod:`topomap.navigate` does)."""
    cfg = NavigateConfig()
    budget, base, replans = 0.0, cfg.time_budget_base_s, 0
    for e in events:
        if e["kind"] == "planned":
            budget = base + per_hop * max(1, e["hops"] or 0)
        elif e["kind"] == "replanned":
            replans += 1
            if replans <= cfg.max_replans:
                budget = max(budget, e["t"] + base + per_hop * max(1, e["hops"] or 0))
    return budget


def failure_kind(row: dict) -> tuple[str | None, str | None]:
    """(primary kind, terminal kind) of a failed episode; (None, None) for a success."""
    if row["success"]:
        return None, None
    status, msg = row["status"], row.get("message", "")
    if status == "replayed":
        return "off target", "off target"
    if status == "arrived":
        terminal = "false arrival"
    elif status == "timeout":
        terminal = "timeout"
    elif "could not localize" in msg:
        terminal = "no localization"
    elif "gave up" in msg:
        terminal = ("gave up (lost)" if "lost sight" in msg else "gave up (fooled)" if "fooled" in msg
                    else "gave up (blocked)" if "blocked on the way" in msg else "gave up (stuck)")
    else:
        terminal = "failed (other)"
    wrong = (row.get("start_localization_error_m", 0.0) > WRONG_START_M
             or row.get("start_localization_error_deg", 0.0) > WRONG_START_DEG)
    return ("wrong start localization" if wrong else terminal), terminal


def draw(maps: list[Path], specs: list[dict], n: int, seed: int, start_offset: float, max_hops: int) -> list[dict]:
    rng = np.random.default_rng(seed)
    per = [n // len(maps) + (i < n % len(maps)) for i in range(len(maps))]
    out = []
    for spec, path, k in zip(specs, maps, per):
        eps = bench.draw_episodes(path, spec["seed"], k, rng, start_offset, max_hops, 1000 * spec["seed"])
        out.append([{**asdict(e), "start_pose": list(e.start_pose)} for e in eps])
    return out


# ---------------------------------------------------------------------- summary
def wilson(k: int, n: int) -> tuple[float, float]:
    """95 % Wilson score interval of k successes in n trials."""
    from scipy.stats import binomtest

    if n == 0:
        return math.nan, math.nan
    ci = binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
    return float(ci.low), float(ci.high)


def summarize(rows: list[dict]) -> dict:
    def stats(sel: list[dict]) -> dict:
        err = np.array([r["final_position_error_m"] for r in sel])
        k = int(sum(r["success"] for r in sel))
        lo, hi = wilson(k, len(sel))
        kinds: dict[str, int] = {}
        for r in sel:
            if r["kind"]:
                kinds[r["kind"]] = kinds.get(r["kind"], 0) + 1
        return {"episodes": len(sel), "arrived": k, "success_rate": k / len(sel), "wilson95": [lo, hi],
                "median_error_m": float(np.median(err)), "p90_error_m": float(np.percentile(err, 90)),
                "median_heading_error_deg": float(np.median([r["final_heading_error_deg"] for r in sel])),
                "median_wall_s": float(np.median([r["wall_s"] for r in sel])),
                "failures": dict(sorted(kinds.items(), key=lambda kv: -kv[1]))}

    out: dict = {}
    for method in METHODS:
        sel = [r for r in rows if r["method"] == method]
        if not sel:
            continue
        out[method] = {"all": stats(sel)}
        for v in ("unicycle", "omni"):
            if vs := [r for r in sel if r["vehicle"] == v]:
                out[method][v] = stats(vs)
    if "topomap" in out:
        base = out["topomap"]["all"]["median_error_m"]
        for method in METHODS[1:]:
            if method in out:
                out[method]["all"]["error_ratio_vs_topomap"] = out[method]["all"]["median_error_m"] / max(base, 1e-9)
        early = [r for r in rows if r["method"] == "topomap" and r["status"] == "failed" and "gave up" in r.get("message", "")
                 and r.get("budget_s") and (r["budget_s"] - r["duration_s"]) > 0.25 * r["budget_s"]]
        out["topomap"]["gave_up_with_quarter_budget_left"] = len(early)
        failed = [r for r in rows if r["method"] == "topomap" and not r["success"] and "wrong_relocalizations" in r]
        if any("wrong_relocalizations" in r for r in rows):  # logs of before this count lack it
            out["topomap"]["failures_with_a_wrong_relocalization"] = sum(r["wrong_relocalizations"] > 0 for r in failed)
    return out


def print_table(summary: dict, title: str, wall_s: float | None = None) -> None:
    print(f"\n{title}")
    print(f"{'method':<14} {'vehicle':<9} {'n':>4} {'success':>8} {'95% Wilson':>15} {'median err':>11} {'p90 err':>9} "
          f"{'median hdg':>11} {'ratio':>6} {'wall/ep':>8}")
    for method, by in summary.items():
        for v, s in by.items():
            if not isinstance(s, dict):
                continue
            ratio = s.get("error_ratio_vs_topomap")
            lo, hi = s["wilson95"]
            print(f"{method:<14} {v:<9} {s['episodes']:>4} {s['success_rate']:>8.1%} {f'{lo:.1%}-{hi:.1%}':>15} "
                  f"{s['median_error_m']:>9.3f} m {s['p90_error_m']:>7.3f} m {s['median_heading_error_deg']:>7.1f} deg "
                  f"{(f'{ratio:.1f}x' if ratio is not None else ''):>6} {s['median_wall_s']:>6.1f} s")
    for method, by in summary.items():
        fails = by["all"]["failures"]
        if fails:
            print(f"{method} failures: " + ", ".join(f"{k} {v}" for k, v in fails.items()))
    if "topomap" in summary:
        print(f"topomap episodes that gave up with more than a quarter of their time budget left: "
              f"{summary['topomap']['gave_up_with_quarter_budget_left']}")
        if "failures_with_a_wrong_relocalization" in summary["topomap"]:
            print(f"topomap failures with a wrong re-localization (> {WRONG_START_M} m or {WRONG_START_DEG:.0f} deg "
                  f"from the truth): {summary['topomap']['failures_with_a_wrong_relocalization']}")
    print("(ratio: the method's median position error / topomap's"
          + (f"; total wall time {wall_s / 60:.1f} min)" if wall_s is not None else ")"))


def runs_baseline(k: int, w: int, every: int) -> bool:
    """Does the (slow) uncompensated servo run episode ``k`` of the ``w``-th world? Every ``every``-th
    episode of each world, shifted by the world's position, so that the baseline spreads over the
    worlds even when their number is a multiple of ``every`` (counting jobs in the interleaved order
    put every baseline episode on the first world)."""
    return (k + w) % max(1, every) == 0


def config_overrides(base, spec: str | None, option: str = "--servo"):
    """``base`` with the ``key=number,...`` of ``spec`` (its numeric fields; an ablation such as
    ``pose_window=1`` of a ServoConfig, ``arrive_floor_max_m=0.12`` of a NavigateConfig), parsed as
    the conditions and disturbance options are."""
    if not spec:
        return base
    numeric = {f.name: f.type for f in fields(base) if f.type in ("int", "float")}
    # the base preset is the method's, named first, so that every item of spec must be key=value
    _, items = preset_with_overrides("none," + spec, option, {"none": base}, numeric)
    values = {}
    for key, val in items:
        whole = numeric[key] == "int"
        try:
            values[key] = int(val) if whole else float(val)
        except ValueError:
            raise ConfigError(f"{option} {key}={val!r} must be {'a whole number' if whole else 'a number'}") from None
    return replace(base, **values)  # the config checks the values themselves


def _job_key(job: dict) -> str:
    return json.dumps(job, sort_keys=True)


def read_log(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def parse_worlds(text: str) -> list[int]:
    seeds: list[int] = []
    for part in text.split(","):
        a, sep, b = part.strip().partition("-")
        seeds += list(range(int(a), int(b) + 1)) if sep else [int(a)]
    return seeds


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=100, help="episodes in all, split over the worlds")
    ap.add_argument("--worlds", default="100-109", help="world seeds, e.g. 100-109 or 100,105 (held out: 100-129)")
    ap.add_argument("--style", default="default", help="world style: default (half photographs) or office (plain paint)")
    ap.add_argument("--conditions", default=None, help="repeat-run conditions: a preset (lighting, evening, moved, "
                                                       "noisy-camera) or key=value,... (default: nominal)")
    ap.add_argument("--teach-conditions", default=None, help="teach-run conditions (default: nominal)")
    ap.add_argument("--disturbance", default="harsh")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--start-offset", type=float, default=0.4, help="start up to this far from the start keyframe [m]")
    ap.add_argument("--max-hops", type=int, default=0, help="only goals at most this many route hops away (0: anywhere)")
    ap.add_argument("--budget-per-hop", type=float, default=10.0, help="time budget: 60 s + this per route hop [s]")
    ap.add_argument("--baseline-every", type=int, default=1,
                    help="run the (slow) uncompensated servo on every N-th episode only (paired; 1: all)")
    ap.add_argument("--servo", default=None,
                    help="servo settings over the presets, key=value,... (an ablation, e.g. pose_window=1)")
    ap.add_argument("--navigate", default=None,
                    help="navigator settings, key=value,... (an ablation, e.g. distrust_loop_after=0)")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--seed", type=int, default=16, help="seed of the episode draw")
    ap.add_argument("--cache", type=Path, default=None, help="folder for texture sets, teach runs and maps (reused)")
    ap.add_argument("--json", type=Path, default=None, help="write every episode and the summary here")
    ap.add_argument("--log", type=Path, default=None, help="append each finished row here (JSON lines)")
    ap.add_argument("--summarize", type=Path, default=None, help="only print the summary of this log")
    ap.add_argument("--resume", action="store_true", help="keep the rows already in --log and run only the missing ones")
    ap.add_argument("--allow-tuning-worlds", action="store_true", help="allow seeds below 100 (then not a held-out figure)")
    args = ap.parse_args(argv)
    if args.summarize is not None:
        rows = read_log(args.summarize)
        print_table(summarize(rows), f"{args.summarize}: {len(rows)} rows")
        return 0
    methods = [m.strip() for m in args.methods.split(",")]
    if unknown := set(methods) - set(METHODS):
        ap.error(f"unknown methods {sorted(unknown)}; choose from {', '.join(METHODS)}")
    seeds = parse_worlds(args.worlds)
    if (tuned := [s for s in seeds if s in TUNING_WORLDS]) and not args.allow_tuning_worlds:
        ap.error(f"worlds {tuned} are tuning worlds; the held-out seeds are {HELD_OUT_WORLDS.start}-"
                 f"{HELD_OUT_WORLDS.stop - 1} (or pass --allow-tuning-worlds)")
    if args.style not in ("default", "office"):
        ap.error("--style must be default or office")
    from topomap.sim.conditions import parse_conditions
    from topomap.sim.vehicle import parse_disturbance

    for spec in (args.conditions, args.teach_conditions):
        parse_conditions(spec)
    parse_disturbance(args.disturbance)
    try:
        config_overrides(servo_preset("default"), args.servo)
        config_overrides(NavigateConfig(), args.navigate, "--navigate")
    except ConfigError as e:
        ap.error(str(e))
    cache = args.cache or Path(tempfile.mkdtemp(prefix="bench_unseen_"))
    cache.mkdir(parents=True, exist_ok=True)
    log = args.log or (args.json.with_suffix(".jsonl") if args.json else cache / "run.jsonl")
    done = read_log(log) if args.resume and log.is_file() else []
    if not args.resume:
        log.write_text("")

    t0 = time.perf_counter()
    specs = [world_spec(s, k, args.style) for k, s in enumerate(seeds)]
    for spec in specs:  # the texture sets, made once before the workers need them
        if spec["textures"]:
            texture_folder(spec["textures"], cache)
    with ProcessPoolExecutor(args.jobs) as pool:
        maps = list(pool.map(prepare, specs, [cache] * len(specs), [args.teach_conditions] * len(specs)))
        print(f"worlds {seeds} ({args.style}; textures {', '.join(sorted({s['textures'] or 'plain' for s in specs}))}): "
              f"maps ready in {time.perf_counter() - t0:.0f} s ({cache})", flush=True)
        drawn = draw(maps, specs, args.episodes, args.seed, args.start_offset, args.max_hops)
        jobs: list[dict] = []
        # episodes in order, worlds interleaved, each by every method (the uncompensated servo on
        # runs_baseline only): a run cut short is still paired and covers every world
        for k in range(max(len(d) for d in drawn)):
            for w, (path, eps) in enumerate(zip(maps, drawn)):
                if k >= len(eps):
                    continue
                for m in methods:
                    if m == "uncompensated" and not runs_baseline(k, w, args.baseline_every):
                        continue
                    jobs.append({"map": str(path), "episode": eps[k], "method": m, "disturbance": args.disturbance,
                                 "budget_per_hop": args.budget_per_hop, "conditions": args.conditions,
                                 **({"servo": args.servo} if args.servo else {}),
                                 **({"navigate": args.navigate} if args.navigate else {})})
        keys = {_job_key(r["job"]) for r in done}
        rows = list(done)
        futures = [pool.submit(run_one, job) for job in jobs if _job_key(job) not in keys]
        if done:
            print(f"resuming: {len(done)} rows in {log}, {len(futures)} to run", flush=True)
        with log.open("a") as f:
            for fut in as_completed(futures):
                row = fut.result()
                rows.append(row)
                f.write(json.dumps(row) + "\n")
                f.flush()
                print(f"world {row['world']} ep {row['episode']:>2} {row['vehicle']:<8} {row['method']:<13} "
                      f"{row['start_node'] if row['start_node'] is not None else '?':>3} -> {row['goal']:<3} {row['status']:<8} "
                      f"{'ok  ' if row['success'] else 'FAIL'} {row['final_position_error_m']:.3f} m "
                      f"{row['final_heading_error_deg']:5.1f} deg  {row['wall_s']:.0f} s  {row['kind'] or ''}", flush=True)
    wall = time.perf_counter() - t0
    rows.sort(key=lambda r: (r["world"], r["episode"], METHODS.index(r["method"])))
    summary = summarize(rows)
    title = (f"held-out worlds {args.worlds} ({args.style}), repeat conditions {args.conditions or 'nominal'}, "
             f"{args.disturbance} disturbances, goals {'anywhere' if not args.max_hops else f'<= {args.max_hops} hops'}")
    print_table(summary, title, wall)
    if args.json is not None:
        args.json.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, "summary": summary,
                                         "episodes": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    from topomap.errors import TopomapError

    try:
        sys.exit(main())
    except TopomapError as e:  # bad input (e.g. a conditions spec): one line, no traceback
        sys.exit(f"Error: {e}")
