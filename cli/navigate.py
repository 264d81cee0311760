"""``topomap navigate``: drive a simulated robot to a map node from images alone (or run the demo)."""

from __future__ import annotations

import functools
import math
from pathlib import Path
from typing import Optional

import typer

from topomap.errors import DatasetError, TopomapError
from topomap_cli.app import app, console, err_console, fail, print_json

_RESULT_KEYS = ("success", "final_position_error_m", "final_heading_error_deg", "path_length_m",
                "teach_path_length_m", "duration_s", "subgoals_reached", "replans", "status")


def _shown(result) -> dict:
    """The result keys the CLI prints (and writes to result.json with --record)."""
    return {k: v for k, v in result.to_dict().items() if k in _RESULT_KEYS or k in ("message", "goal", "start_node")}


def _start_pose(text: str) -> tuple[float, float, float]:
    try:
        x, z, th = (float(v) for v in text.split(","))
    except ValueError:
        fail(f"--start-pose {text!r} must be x,z,theta (metres, metres, radians), e.g. 12.0,8.0,0.0")
    if not all(math.isfinite(v) for v in (x, z, th)):
        fail(f"--start-pose {text!r} must hold finite numbers")
    return x, z, th


def _printer(quiet: bool):
    from topomap.navigate import EventKind

    def show(ev) -> None:
        if quiet or ev.kind is EventKind.STEP:
            return
        style = {"arrived": "green", "failed": "red", "timeout": "red", "lost": "yellow"}.get(ev.kind.value, "dim")
        err_console.print(f"[{style}]{ev.time_s:7.1f} s  {ev.kind.value:<10}[/] {ev.message}")

    return show


def _report(data: dict, as_json: bool, files: dict | None = None) -> None:
    if as_json:
        print_json(data)
    else:
        ok = data["success"]
        console.print(
            f"[{'green' if ok else 'red'}]{'arrived' if ok else 'did not arrive'}[/] ({data['status']}): "
            f"final error {data['final_position_error_m']:.3f} m, {data['final_heading_error_deg']:.1f} deg; "
            f"drove {data['path_length_m']:.1f} m (teach route {data['teach_path_length_m']:.1f} m) in "
            f"{data['duration_s']:.0f} s; {data['subgoals_reached']} subgoals, {data['replans']} re-plans"
            + ("" if ok or not data.get("message") else f" — {data['message']}"),
            highlight=False,
        )
        for name, path in (files or {}).items():
            console.print(f"  {name:<11} {path}", highlight=False)
    if not data["success"]:
        raise typer.Exit(1)


@app.command()
def navigate(
    map_path: Optional[Path] = typer.Argument(None, metavar="[MAP]", help="Map built from a simulator teach run. Without it: the built-in demo."),
    goal: Optional[int] = typer.Option(None, "--goal", help="Goal node id."),
    start_node: Optional[int] = typer.Option(None, "--start-node", help="Start at this node's keyframe pose (and tell the navigator)."),
    start_pose: Optional[str] = typer.Option(None, "--start-pose", help="Start pose x,z,theta [m, m, rad]; the navigator localizes itself."),
    world: Optional[str] = typer.Option(None, "--world", help="World: 'default', a seed, 'office[:SEED]' or a world JSON [default: the map's teach world]."),
    textures: Optional[Path] = typer.Option(None, "--textures", help="Folder of photographs for the walls (as `topomap sim teach --textures`)."),
    conditions: Optional[str] = typer.Option(None, "--conditions", help="Repeat-run conditions: none, lighting, evening, moved, noisy-camera and/or key=value,... [default: as taught]."),
    poses: Optional[Path] = typer.Option(None, "--poses", help="Teach poses CSV, for scoring only [default: poses.csv of the map's teach run]."),
    vehicle: str = typer.Option("unicycle", "--vehicle", help="unicycle or omni."),
    disturbance: Optional[str] = typer.Option(None, "--disturbance", help="Unknown input disturbance: none, bias, sinusoidal, slip, noisy, harsh, and/or key=value,... [default: none; demo: bias]."),
    servo: str = typer.Option("default", "--servo", help="Servo preset: default, uncompensated, aicardi, floor."),
    seed: int = typer.Option(0, "--seed", help="Seed of the disturbance's random parts."),
    record: Optional[Path] = typer.Option(None, "--record", help="Folder for trajectory.png, camera.gif (and camera.mp4 with the viz extra), events.jsonl, result.json."),
    rerun: Optional[Path] = typer.Option(None, "--rerun", help="Write a Rerun recording of the run (FILE.rrd): camera with matches, subgoal keyframe, estimated and true trajectory, map graph, servo estimates and commands, events (needs the viz extra)."),
    rerun_spawn: bool = typer.Option(False, "--rerun-spawn", help="Stream the run to a Rerun viewer started for it (needs a display and the viz extra)."),
    out: Path = typer.Option(Path("topomap-demo"), "--out", help="Demo output folder (no MAP)."),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON."),
) -> None:
    """Navigate to a node from images alone, in simulation; without MAP, run the built-in demo."""
    from topomap.config import servo_preset
    from topomap.motion import vehicle_kind
    from topomap.sim.vehicle import parse_disturbance

    vehicle_kind(vehicle)
    servo_cfg = servo_preset(servo)
    if start_node is not None and start_pose is not None:
        fail("give either --start-node or --start-pose, not both")
    if map_path is None:
        if any(v is not None for v in (goal, start_node, start_pose, world, poses, record, textures, conditions)):
            fail("--goal, --start-*, --world, --textures, --conditions, --poses and --record need a MAP "
                 "(without MAP the demo chooses them)")
        _demo(out, vehicle, disturbance, seed, as_json, rerun, rerun_spawn)
        return
    if goal is None:
        fail("give the goal node with --goal N (see `topomap info MAP` for the node ids)")
    parse_disturbance(disturbance or "none")
    from topomap.sim.conditions import parse_conditions

    if conditions is not None:
        parse_conditions(conditions)

    from topomap.groundtruth import read_poses
    from topomap.sim.demo import EpisodeRecorder
    from topomap.sim.episode import goal_pose, run_episode
    from topomap.store import load_map, load_node_image

    _check_rerun(rerun)
    m = load_map(map_path, images=record is not None or rerun is not None or rerun_spawn)  # keyframes for the drawings
    m.node(goal)
    if start_node is not None:
        from topomap.plan import Planner

        Planner(m).route(start_node, goal)  # no path between them: a clear error before the robot moves
    teach_dir = Path(m.sequences[0]["source"]) if m.sequences else None
    w, taught_conditions = _teach_world(m, world, textures, teach_dir)
    if poses is None:
        if teach_dir is None or not (teach_dir / "poses.csv").is_file():
            raise DatasetError(f"no poses.csv beside the map's images ({teach_dir}); give --poses CSV")
        poses = teach_dir / "poses.csv"
    pose_table = read_poses(poses)
    goal_pose(m, pose_table, goal)  # the scorer needs the goal's teach pose
    if record is not None:
        if record.exists() and not record.is_dir():
            fail(f"--record {record} exists and is not a folder")
        record.mkdir(parents=True, exist_ok=True)
    pose = _start_pose(start_pose) if start_pose is not None else None
    if pose is not None and not w.is_free(pose[0], pose[1]):
        fail(f"--start-pose {start_pose} is not on the world's free floor")
    rec = EpisodeRecorder(m) if record is not None else None
    viewer = _rerun_logger(m, w, pose_table, rerun, rerun_spawn)
    show = _printer(as_json)

    def listen(ev) -> None:
        show(ev)
        if rec is not None:
            rec(ev)
        if viewer is not None:
            viewer(ev)

    result = run_episode(m, w, goal, pose_table, start_pose=pose, start_node=start_node, vehicle=vehicle,
                         disturbance=disturbance or "none", seed=seed, servo_config=servo_cfg, on_event=listen,
                         on_truth=viewer.log_truth if viewer is not None else None,
                         conditions=conditions if conditions is not None else taught_conditions,
                         keyframe_image=functools.partial(load_node_image, map_path))
    data = _shown(result)
    files = rec.write_all(record, w, pose_table, result, data=data) if rec is not None else {}
    if viewer is not None and viewer.close() is not None:
        files["rerun"] = rerun
    _report(data, as_json, files)


def _teach_world(m, world: str | None, textures: Path | None, teach_dir: Path | None):
    """The world to drive in and the teach run's conditions: ``--world`` (with ``--textures``, as
    ``sim teach``), else the world the map remembers (meta ``teach_world``), else world.json beside
    the map's teach images (maps built before the key existed)."""
    from topomap.build import TEACH_WORLD_KEY
    from topomap.sim.conditions import parse_conditions
    from topomap.sim.world import World, resolve_world

    taught = m.meta.get(TEACH_WORLD_KEY) or {}
    try:
        taught_conditions = parse_conditions(taught.get("conditions"))
    except TopomapError as e:
        raise DatasetError(f"the map's teach world has unreadable conditions ({e}); give --conditions") from None
    if world is not None:
        return resolve_world(world, textures=textures), taught_conditions
    if taught.get("world") is not None:
        w = World.from_dict(taught["world"], source="the map's teach world")
        return (w if textures is None else w.retextured(textures)), taught_conditions
    if teach_dir is None or not (teach_dir / "world.json").is_file():
        raise DatasetError(f"the map does not remember its teach world and there is no world.json beside its images "
                           f"({teach_dir}); give --world SEED|FILE")
    return resolve_world(str(teach_dir / "world.json"), textures=textures), taught_conditions


def _check_rerun(path: Path | None) -> None:
    """One-line errors for a --rerun file that cannot be written, before the robot moves."""
    if path is None:
        return
    if path.is_dir():
        fail(f"--rerun {path} is a folder; give a file name ending in .rrd")
    if path.suffix.lower() != ".rrd":
        fail(f"--rerun {path.name}: a Rerun recording's file name ends in .rrd")
    if not path.parent.exists():
        fail(f"folder {path.parent} does not exist (for --rerun)")


def _rerun_logger(m, world, poses, path: Path | None, spawn: bool):
    """The run's Rerun logger (keyframe poses from the teach run, for the floor plan), or None."""
    if path is None and not spawn:
        return None
    from topomap.viz.rerun import RerunLogger

    node_poses = {n: poses[node.source] for n, node in m.nodes.items() if node.source in poses}
    viewer = RerunLogger(m, path, spawn=spawn, node_poses=node_poses)
    viewer.log_world(world)
    return viewer


def _demo(out: Path, vehicle: str, disturbance: str | None, seed: int, as_json: bool,
          rerun: Path | None = None, rerun_spawn: bool = False) -> None:
    from topomap.sim.demo import DEMO_DISTURBANCE, run_demo

    if out.exists() and not out.is_dir():
        fail(f"--out {out} exists and is not a folder")
    _check_rerun(rerun)
    if rerun is not None or rerun_spawn:
        from topomap.viz.rerun import check_rerun

        check_rerun(rerun_spawn)  # a missing extra or viewer fails now, not after teaching and building
    show = _printer(as_json)
    demo = run_demo(out, vehicle=vehicle, disturbance=disturbance or DEMO_DISTURBANCE, seed=seed,
                    on_stage=(None if as_json else lambda s: err_console.print(f"[bold]{s}[/]")), on_event=show,
                    rerun=rerun, rerun_spawn=rerun_spawn)
    data = _shown(demo.result)
    _report(data, as_json, {k: str(v) for k, v in demo.files.items()})
