"""``topomap sim ...``: simulated worlds, teach runs and floor plans (a thin layer over :mod:`topomap.sim`)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import typer

from topomap_cli.app import app, console, err_console, fail, print_json

sim_app = typer.Typer(
    help="Simulated indoor worlds: teach runs, floor plans, single renders.",
    no_args_is_help=True,
    context_settings={"help_option_names": ["-h", "--help"]},
)
app.add_typer(sim_app, name="sim")

_WORLD_HELP = "World: 'default', a seed (integer), 'office[:SEED]' (plain office walls) or a world JSON file."
_CONDITIONS_HELP = "How the run looks: none, lighting, evening, moved, noisy-camera and/or key=value,... (topomap.sim.conditions)."
_TEXTURES_HELP = "Folder of your own photographs (.jpg/.png) for the walls."


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        fail(f"--size {text!r} must look like 320x240")
    if not (16 <= w <= 4096 and 16 <= h <= 4096):
        fail(f"--size {text!r} must be between 16x16 and 4096x4096")
    return w, h


#: Image files the sim commands write (chosen by the -o suffix).
_IMAGE_OUT = (".png", ".jpg", ".jpeg", ".bmp")
_PLOT_OUT = (".png", ".jpg", ".jpeg", ".svg", ".pdf")


def _check_out(path: Path, suffixes: tuple[str, ...]) -> None:
    """One line, before any work, for an output file that cannot be written."""
    if path.is_dir():
        fail(f"{path} is a folder; give a file name inside it")
    if not path.parent.exists():
        fail(f"folder {path.parent} does not exist")
    if path.suffix.lower() not in suffixes:
        fail(f"cannot write {path.name}: give a file name ending in one of {', '.join(suffixes)}")


def _world(spec: str, textures: Optional[Path]):
    from topomap.sim.world import resolve_world

    return resolve_world(spec, textures=textures)


@sim_app.command("teach")
def teach_cmd(
    out: Path = typer.Option(..., "--out", "-o", help="Output folder for images, poses.csv, camera.yaml."),
    world: str = typer.Option("default", "--world", "-w", help=_WORLD_HELP),
    route: str = typer.Option("loop", "--route", "-r", help="Route to drive: loop, room1, ... (see show-world)."),
    vehicle: str = typer.Option("unicycle", "--vehicle", help="unicycle or omni."),
    disturbance: str = typer.Option("none", "--disturbance", "-d", help="Preset (none, bias, sinusoidal, slip, noisy, harsh) and/or key=value,..."),
    textures: Optional[Path] = typer.Option(None, "--textures", help=_TEXTURES_HELP),
    spacing: float = typer.Option(0.25, "--spacing", help="Metres of travel between images."),
    size: str = typer.Option("320x240", "--size", help="Image size WIDTHxHEIGHT (60 degree horizontal field of view)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the disturbance's random walk."),
    conditions: str = typer.Option("none", "--conditions", help=_CONDITIONS_HELP),
    force: bool = typer.Option(False, "--force", help="Overwrite a previous teach run in the output folder."),
    json_out: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
) -> None:
    """Drive a route with a ground-truth driver and record images, poses.csv and camera.yaml."""
    from rich.progress import BarColumn, Progress, TextColumn

    from topomap.sim.simulator import default_camera
    from topomap.sim.teach import TeachConfig, teach
    from topomap.sim.vehicle import parse_disturbance
    from topomap.motion import vehicle_kind

    vehicle_kind(vehicle)  # fail early on a bad choice
    parse_disturbance(disturbance)
    from topomap.sim.conditions import parse_conditions

    parse_conditions(conditions)
    w, h = _size(size)
    cfg = TeachConfig(spacing_m=spacing)
    wld = _world(world, textures)
    wld.route(route)
    with Progress(TextColumn("teach {task.description}"), BarColumn(), TextColumn("{task.fields[frames]} images"),
                  console=err_console, transient=True, disable=json_out) as progress:
        task = progress.add_task(route, total=1.0, frames=0)
        res = teach(
            wld, route, out, config=cfg, vehicle=vehicle, disturbance=disturbance, camera=default_camera(w, h),
            seed=seed, overwrite=force, conditions=conditions,
            on_progress=lambda n, f: progress.update(task, completed=f, frames=n),
        )
    summary = {
        "out": str(res.out_dir), "world": wld.name, "route": res.route, "frames": res.frames,
        "length_m": round(res.length_m, 3), "duration_s": round(res.duration_s, 2), "collisions": res.collisions,
        "poses": str(res.poses_path), "camera": str(res.camera_path), "world_file": str(res.world_path),
    }
    if json_out:
        print_json(summary)
        return
    console.print(
        f"{res.frames} images of route {res.route!r} ({res.length_m:.1f} m, {res.duration_s:.0f} s simulated) "
        f"in {res.out_dir}; build a map with: topomap build {res.out_dir} --camera {res.camera_path} -o map.topomap"
    )


@sim_app.command("show-world")
def show_world_cmd(
    world: str = typer.Argument(..., help=_WORLD_HELP),
    out: Path = typer.Option(..., "--out", "-o", help="PNG file to write."),
    route: Optional[str] = typer.Option(None, "--route", "-r", help="Route to draw (default: loop if present)."),
    json_out: bool = typer.Option(False, "--json", help="Print the world's summary as JSON."),
) -> None:
    """Draw a world's floor plan and one of its routes."""
    from topomap.sim.plot import plot_world

    _check_out(out, _PLOT_OUT)
    wld = _world(world, None)
    if route is None and "loop" in wld.route_names:
        route = "loop"
    plot_world(wld, out, route=route)
    info = {
        "world": wld.name, "seed": wld.seed, "walls": len(wld.walls), "bounds_m": [round(v, 3) for v in wld.bounds()],
        "routes": {r.name: round(r.length_m, 2) for r in wld.routes}, "plot": str(out),
    }
    if json_out:
        print_json(info)
        return
    routes = ", ".join(f"{n} ({m} m)" for n, m in info["routes"].items())
    console.print(f"{wld.name}: {len(wld.walls)} wall panels; routes: {routes}; plan written to {out}")


@sim_app.command("make-world")
def make_world_cmd(
    out: Path = typer.Option(..., "--out", "-o", help="World JSON file to write."),
    seed: int = typer.Option(0, "--seed", help="Seed of the floor plan and textures."),
    lattice: str = typer.Option("3x3", "--lattice", help="Junctions along x and z, e.g. 4x3."),
    rooms: int = typer.Option(4, "--rooms", help="Rooms to attach."),
    textures: Optional[Path] = typer.Option(None, "--textures", help=_TEXTURES_HELP),
) -> None:
    """Generate a world from a seed and save it as JSON."""
    from topomap.sim.world import generate_world

    _check_out(out, (".json",))
    nx_, nz_ = _size_pair(lattice)
    wld = generate_world(seed, lattice=(nx_, nz_), rooms=rooms, textures=textures)
    try:
        wld.save(out)
    except OSError as e:
        fail(f"cannot write {out}: {e.strerror or e}")
    console.print(f"{wld.name}: {len(wld.walls)} wall panels, routes {', '.join(wld.route_names)} -> {out}")


def _size_pair(text: str) -> tuple[int, int]:
    try:
        a, b = (int(v) for v in text.lower().split("x"))
    except ValueError:
        fail(f"--lattice {text!r} must look like 3x3")
    return a, b


@sim_app.command("render")
def render_cmd(
    world: str = typer.Argument(..., help=_WORLD_HELP),
    out: Path = typer.Option(..., "--out", "-o", help="PNG file to write."),
    pose: Optional[str] = typer.Option(None, "--pose", help="x,z,theta [m, m, deg]; default: the start of the loop route."),
    size: str = typer.Option("320x240", "--size", help="Image size WIDTHxHEIGHT."),
    textures: Optional[Path] = typer.Option(None, "--textures", help=_TEXTURES_HELP),
    conditions: str = typer.Option("none", "--conditions", help=_CONDITIONS_HELP),
    seed: int = typer.Option(0, "--seed", help="Seed of the camera noise (with --conditions)."),
) -> None:
    """Render the camera image at one pose (handy to look at a world)."""
    import cv2

    from topomap.sim.geometry import Pose
    from topomap.sim.simulator import Simulator, default_camera

    _check_out(out, _IMAGE_OUT)
    wld = _world(world, textures)
    start = None
    if pose is not None:
        try:
            x, z, th = (float(v) for v in pose.split(","))
        except ValueError:
            fail(f"--pose {pose!r} must be x,z,theta with theta in degrees, like 12.5,8,90")
        start = Pose(x, z, math.radians(th))
    w, h = _size(size)
    with Simulator(wld, camera=default_camera(w, h), start_pose=start, conditions=conditions, seed=seed) as sim:
        img = sim.robot.render()
    if not cv2.imwrite(str(out), cv2.cvtColor(img, cv2.COLOR_RGB2BGR)):
        fail(f"cannot write image {out}; use a .png path in a writable folder")
    console.print(f"{w}x{h} image written to {out}")
