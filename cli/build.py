"""``topomap build | info | show | export | index``: make and inspect map files."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import time
from pathlib import Path

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table
from rich.text import Text

from topomap.build import BuildProgress, build_index, build_map, calibrate
from topomap.calibration import Calibration
from topomap.camera import load_camera
from topomap.config import BUILD_PRESETS, build_preset
from topomap.errors import CalibrationError, DatasetError
from topomap.features import detector
from topomap.groundtruth import right_nodes
from topomap.images import open_sequence
from topomap.parallel import make_executor
from topomap.relative_motion import annotate_edges
from topomap.self_supervision import calibrate_on_queries
from topomap.store import (
    check_writable,
    export_graphml,
    export_json,
    load_map,
    open_for_update,
    save_map,
    upgrade_map,
)
from topomap_cli.app import app, console, err_console, fail, print_json
from topomap_cli.localize import GROUND_TRUTH_HELP, read_truth


class _RateColumn(TextColumn):
    """Items per second of a task (its ``unit`` field names the items)."""

    def __init__(self):
        super().__init__("")

    def render(self, task):
        speed = task.finished_speed or task.speed
        unit = task.fields.get("unit", "frames")
        return Text(f"{speed:5.1f} {unit}/s" if speed else f"      {unit}/s", style="cyan")


def _progress_bar(quiet: bool):
    return Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), _RateColumn(),
        TimeElapsedColumn(), TextColumn("{task.fields[info]}"),
        console=err_console, transient=False, disable=quiet,
    )


#: File types `topomap show` writes (chosen by the -o suffix).
SHOW_FORMATS = ("png", "jpg", "jpeg", "svg", "pdf")


def _check_output_file(path: Path, suffixes: tuple[str, ...] | None = None) -> None:
    """One-line errors for an output file that cannot be written, before any work is done."""
    if path.is_dir():
        fail(f"{path} is a folder; give a file name inside it")
    if not path.parent.exists():
        fail(f"folder {path.parent} does not exist")
    if suffixes is not None and path.suffix.lower().lstrip(".") not in suffixes:
        fail(f"cannot write {path.name}: give a file name ending in one of {', '.join('.' + s for s in suffixes)}")


@app.command()
def build(
    source: Path = typer.Argument(..., help="Image folder, video file, text file listing image paths, or a ROS bag (.bag, .mcap, .db3, rosbag2 folder)."),
    output: Path = typer.Option(..., "--output", "-o", help="Map file to write (e.g. office.topomap)."),
    features: str = typer.Option(None, "--features", "-f", help=f"Local features: {', '.join(sorted(['orb', 'sift', 'akaze']))} [default: the preset's, orb]."),
    max_features: int = typer.Option(None, "--max-features", help="Keypoints kept per image."),
    resize: int = typer.Option(None, "--resize", help="Shrink images so the longest side is at most MAXPX.", metavar="MAXPX"),
    camera: Path = typer.Option(None, "--camera", help="Intrinsics YAML/JSON (fx, fy, cx, cy[, distortion]); default: a bag's CameraInfo, else 60 deg field of view."),
    topic: str = typer.Option(None, "--topic", help="Image topic of a ROS bag (sensor_msgs/Image or CompressedImage); omitted: the bag's only one."),
    preset: str = typer.Option("default", "--preset", help=f"Build preset: {', '.join(BUILD_PRESETS)}."),
    every: int = typer.Option(1, "--every", help="Use every N-th frame (videos and folders)."),
    append: bool = typer.Option(False, "--append", help="Add this sequence to the existing map, linked by loop closures."),
    force: bool = typer.Option(False, "--force", help="Overwrite an existing map file."),
    no_images: bool = typer.Option(False, "--no-images", help="Do not store keyframe images (maps that only localize and navigate; thumbnails stay; no calibration)."),
    no_calibration: bool = typer.Option(False, "--no-calibration", help="Skip the self-supervised calibration of localization confidence (faster; confidences stay raw)."),
    image_quality: int = typer.Option(None, "--image-quality", help="JPEG quality of the stored keyframe images, 1..100 [default: the preset's, 40].", metavar="Q"),
    workers: int = typer.Option(None, "--workers", "-j", help="Worker processes for decoding, features and verification [default: every core]; 1 = in this process.", metavar="N"),
    dask: str = typer.Option(None, "--dask", help="'local': run the work on a Dask LocalCluster of --workers processes (needs the 'cluster' extra).", metavar="local"),
    scheduler: str = typer.Option(None, "--scheduler", help="Run the work on the Dask cluster at this address (tcp://HOST:8786); its workers must read SOURCE at the same path.", metavar="ADDRESS"),
    as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
) -> None:
    """Build a topological map from an image sequence."""
    if append and force:
        fail("--append and --force exclude each other: --append extends the map, --force replaces it")
    if workers is not None and workers < 1:
        fail(f"--workers must be at least 1, got {workers}")
    if append and (no_images or image_quality is not None):
        fail("--no-images and --image-quality are the map's own settings; they cannot change when appending")
    config = build_preset(preset)
    if no_images:
        config = dataclasses.replace(config, store_images=False)
    if no_calibration:
        config = dataclasses.replace(config, calibration=dataclasses.replace(config.calibration, enabled=False))
    if image_quality is not None:
        config = dataclasses.replace(config, image_quality=image_quality)
    if features is not None:
        detector(features)
        config = dataclasses.replace(config, features=dataclasses.replace(config.features, kind=features.lower()))
    if max_features is not None:
        config = dataclasses.replace(config, features=dataclasses.replace(config.features, max_features=max_features))
    if resize is not None:
        config = dataclasses.replace(config, features=dataclasses.replace(config.features, resize_max_px=resize))
    seq = open_sequence(source, every, topic)  # bad sources fail here, before the progress bar appears
    check_writable(output, overwrite=force, append=append)
    cam = load_camera(camera) if camera is not None else None
    if cam is not None and seq.camera is not None and not append:
        err_console.print(f"[dim]--camera {camera.name} is used instead of {seq.camera.source}[/]")
    executor = make_executor(workers, dask=dask, scheduler=scheduler)  # an unreachable scheduler fails here
    with contextlib.ExitStack() as stack:
        # --append: the map's write lock is held from reading the map to the commit, so a concurrent
        # `index` or `--append` waits (or is refused with one line) instead of being overwritten
        stack.enter_context(executor)
        # the map's keyframe images are read too: the calibration refit after appending samples them
        update = stack.enter_context(open_for_update(output, images=True)) if append else None
        base = update.map if update is not None else None
        t0 = time.perf_counter()
        with _progress_bar(as_json) as bar:
            tasks = {"frames": bar.add_task("frames", total=None, info="", unit="frames")}
            labels = {"index": ("vocabulary", "steps"), "loops": ("loop closure", "nodes"),
                      "align": ("alignment", "keyframes"), "motion": ("keyframe-pair geometry", "steps"),
                      "calibrate": ("calibration", "steps")}

            def on_progress(p: BuildProgress) -> None:
                if p.stage not in tasks:
                    label, unit = labels[p.stage]
                    tasks[p.stage] = bar.add_task(label, total=p.total, info="", unit=unit)
                info = f"{p.nodes} nodes" if p.stage == "frames" else f"{p.edges} edges"
                bar.update(tasks[p.stage], total=p.total or None, completed=p.done, info=info)

            m = build_map(seq, None if append and features is None else config, cam, base=base,
                          on_progress=on_progress, executor=executor)
        if update is not None:
            update.commit(m)
        else:
            save_map(m, output, overwrite=force)
        seconds = time.perf_counter() - t0
    run = m.sequences[-1]
    summary = {
        "map": str(output),
        "source": str(source),
        "frames_read": run["frames_read"],
        "frames_skipped": run["frames_skipped"],
        "skipped": run["skipped"],
        "nodes_added": run["nodes_added"],
        "aligned_links_added": run.get("aligned_links_added", 0),
        **{k: v for k, v in m.summary().items() if k in ("nodes", "frames", "edges", "edges_by_kind", "components")},
        "features": m.feature_kind,
        "workers": executor.describe(),
        "seconds": round(seconds, 2),
        "frames_per_second": round(run["frames"] / seconds, 2) if seconds > 0 else None,
        "file_bytes": output.stat().st_size,
    }
    if as_json:
        print_json(summary)
        return
    t = Table(title=f"{'Extended' if append else 'Built'} {output}", show_header=False, box=None, padding=(0, 2))
    t.add_row("frames read", f"{summary['frames_read']}  ({summary['frames_skipped']} skipped)")
    for s in run["skipped"][:5]:
        t.add_row("  skipped", f"{s['frame']}: {s['reason']}")
    t.add_row("nodes", f"{summary['nodes']}  (+{summary['nodes_added']})" if append else str(summary["nodes"]))
    t.add_row("edges", f"{summary['edges']}  " + ", ".join(f"{k} {v}" for k, v in summary["edges_by_kind"].items()))
    if append:
        t.add_row("aligned", f"{summary['aligned_links_added']} keyframes linked by sequence alignment (no verified geometry)")
    t.add_row("components", str(summary["components"]))
    t.add_row("features", f"{m.feature_kind}, working size {m.working_size[0]}x{m.working_size[1]}, camera: {m.camera.source}")
    t.add_row("time", f"{seconds:.1f} s  ({summary['frames_per_second']} frames/s; {summary['workers']})")
    t.add_row("file", f"{output}  ({summary['file_bytes'] / 1e6:.1f} MB)")
    console.print(t)


@app.command()
def info(
    map_path: Path = typer.Argument(..., metavar="MAP", help="Map file."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON."),
) -> None:
    """Summarise a map: nodes, frames, edges by kind, components, features, schema version."""
    m = load_map(map_path)
    from topomap.store import SCHEMA_VERSION

    version = m.meta.get("schema_version", SCHEMA_VERSION)
    data = {**m.summary(), "schema_version": version, "file_bytes": map_path.stat().st_size,
            "created_utc": m.meta.get("created_utc"), "topomap_version": m.meta.get("topomap_version"),
            "build_config": dataclasses.asdict(m.config),
            "sequence_sources": [s.get("source") for s in m.sequences]}
    cal = Calibration.from_meta(m.meta)
    data["calibration"] = cal.to_dict() if cal is not None else None
    if as_json:
        print_json(data)
        return
    t = Table(title=str(map_path), show_header=False, box=None, padding=(0, 2))
    t.add_row("nodes", str(data["nodes"]))
    t.add_row("frames", f"{data['frames']}  ({data['frames_skipped']} skipped)")
    t.add_row("edges", f"{data['edges']}  " + ", ".join(f"{k} {v}" for k, v in data["edges_by_kind"].items()))
    t.add_row("components", str(data["components"]))
    f = data["features"]
    t.add_row("features", f"{f['kind']}: {f['total']} ({f['per_node_mean']:.0f} per node)")
    t.add_row("index", "yes" if data["index"] else "no (run `topomap index`)")
    t.add_row("calibration", _calibration_line(m, map_path))
    t.add_row("experiences", "; ".join(
        f"{x['sequence']}: {Path(str(x['source'])).name} ({x['nodes']} nodes"
        + "".join(f", {n} links to {o}" for o, n in x["links"].items())
        + "".join(f", {n} aligned to {o}" for o, n in x.get("aligned", {}).items()) + ")" for x in data["experiences"]))
    t.add_row("working size", f"{data['working_size'][0]}x{data['working_size'][1]}")
    t.add_row("schema version", str(version) if version == SCHEMA_VERSION
              else f"{version} (read as {SCHEMA_VERSION}; `topomap upgrade {map_path}` rewrites it)")
    t.add_row("file size", f"{data['file_bytes'] / 1e6:.2f} MB")
    console.print(t)


@app.command()
def show(
    map_path: Path = typer.Argument(..., metavar="MAP", help="Map file."),
    output: Path = typer.Option(None, "--output", "-o", help="Image to write (.png, .jpg, .svg, .pdf)."),
    poses: Path = typer.Option(None, "--poses", help="Ground-truth poses CSV (image,x,z[,theta] or image,cx,cy,cz) to place nodes."),
    rerun: Path = typer.Option(None, "--rerun", help="Write a Rerun recording (FILE.rrd): the graph and each keyframe's thumbnail (needs the viz extra)."),
    rerun_spawn: bool = typer.Option(False, "--rerun-spawn", help="Show the map in a Rerun viewer started for it (needs a display)."),
) -> None:
    """Draw the map graph with node thumbnails (loop edges dashed red), as an image and/or in Rerun."""
    from topomap.groundtruth import read_poses

    if output is None and rerun is None and not rerun_spawn:
        fail("give an image to write with -o FILE.png, a Rerun recording with --rerun FILE.rrd, or --rerun-spawn")
    if output is not None:
        _check_output_file(output, SHOW_FORMATS)
    if rerun is not None:
        _check_output_file(rerun, ("rrd",))
    m = load_map(map_path)
    positions = read_poses(poses).positions_2d() if poses else None
    if positions is not None:
        missing = [n.source for n in m.nodes.values() if n.source not in positions]
        if missing:
            raise DatasetError(f"{poses} has no pose for keyframe(s) {', '.join(missing[:3])}; is it the right file?")
    if output is not None:
        from topomap.viz import plot_map

        try:
            plot_map(m, output, positions)
        except OSError as e:
            fail(f"cannot write {output}: {e.strerror or e}")
        err_console.print(f"wrote {output}")
    if rerun is not None or rerun_spawn:
        from topomap.viz.rerun import log_map

        node_xy = {n.id: positions[n.source] for n in m.nodes.values()} if positions is not None else None
        log_map(m, rerun, spawn=rerun_spawn, positions=node_xy)
        if rerun is not None:
            err_console.print(f"wrote {rerun}")


@app.command()
def export(
    map_path: Path = typer.Argument(..., metavar="MAP", help="Map file."),
    fmt: str = typer.Option("json", "--format", help="json or graphml."),
    output: Path = typer.Option(..., "--output", "-o", help="File to write."),
) -> None:
    """Export the graph as JSON or GraphML."""
    fmt = fmt.lower()
    if fmt not in ("json", "graphml"):
        fail(f"unknown format {fmt!r}; choose one of: graphml, json")
    _check_output_file(output)
    m = load_map(map_path)
    try:
        if fmt == "json":
            output.write_text(json.dumps(export_json(m), indent=2) + "\n")
        else:
            export_graphml(m, output)
    except OSError as e:
        fail(f"cannot write {output}: {e.strerror or e}")
    err_console.print(f"wrote {output}")


def _calibration_line(m, map_path: Path) -> str:
    cal = Calibration.from_meta(m.meta)
    if cal is None:
        return f"no: confidences are raw (`topomap index {map_path}` fits one)"
    f = cal.fitted_for
    if f.get("labelled"):
        seq = ("; sequence confidence fitted too" if cal.sequence is not None else
               "; sequence confidence: the filter's posterior (too few of its answers wrong to fit)")
        return (f"fitted on {f.get('samples', '?')} labelled queries ({f.get('right', '?')} answered right), "
                f"descriptor {f.get('descriptor', '?')}{seq}")
    return f"self-supervised, {f.get('samples', '?')} samples ({f.get('right', '?')} right), descriptor {f.get('descriptor', '?')}"


def _labelled(m, query: Path, topic: str | None, truth):
    """(image, right node ids) of each query frame, streamed (a query the ground truth does not
    list has no right node: a place not in the map, as ``topomap eval`` counts it)."""
    good_of = right_nodes(truth, m)
    for f in open_sequence(query, topic=topic):
        yield f.image, good_of(f.name)


@app.command()
def index(
    map_path: Path = typer.Argument(..., metavar="MAP", help="Map file."),
    no_calibration: bool = typer.Option(False, "--no-calibration", help="Rebuild the index only; keep confidences raw."),
    calibrate_on: Path = typer.Option(None, "--calibrate-on", metavar="QUERIES",
                                      help="Fit the calibration on these labelled queries (folder, video, ROS bag; "
                                           "with --ground-truth) instead of the map's own views."),
    topic: str = typer.Option(None, "--topic", help="Image topic of a --calibrate-on ROS bag."),
    ground_truth: str = typer.Option(None, "--ground-truth", help="Of the --calibrate-on queries: " + GROUND_TRUTH_HELP),
    map_poses: Path = typer.Option(None, "--map-poses", help="Poses CSV of the map's frames (with a poses ground truth)."),
    radius: float = typer.Option(None, "--radius", help="Distance [m] within which a map frame shows the query's place."),
    tolerance: int = typer.Option(0, "--tolerance", help="same-name: also accept this many frames before/after."),
) -> None:
    """(Re)build a map's place-recognition index and refit its confidence calibration, in place.

    The calibration is self-supervised (the map's own views) unless --calibrate-on gives labelled
    queries: a traversal with ground truth shows how hard a real one is, which the map's own views
    cannot (docs/localization.md, "Calibration")."""
    if (calibrate_on is None) != (ground_truth is None):
        fail("--calibrate-on and --ground-truth go together: the labelled queries and their ground truth")
    if calibrate_on is not None and no_calibration:
        fail("--calibrate-on fits a calibration; drop --no-calibration")
    # the write lock is held from reading to the commit; keyframe images are read for the calibration
    with open_for_update(map_path, images=not no_calibration) as update:
        m = update.map
        truth = None
        if calibrate_on is not None:  # a wrong ground truth fails before the (slow) index
            truth = read_truth(m, calibrate_on, topic, ground_truth, map_poses, radius, tolerance)
        build_index(m)
        if m.index is None and not m.arrays:
            fail(f"{map_path} has too few features to index")
        annotate_edges(m)  # edges of older maps get their keyframe-pair geometry too
        cal = None
        if truth is not None:
            try:
                cal = calibrate_on_queries(m, _labelled(m, calibrate_on, topic, truth), seed=m.config.seed)
            except CalibrationError as e:
                fail(f"{e} (the map is unchanged)")
        elif not no_calibration:
            m.config = dataclasses.replace(m.config, calibration=dataclasses.replace(m.config.calibration, enabled=True))
            cal = calibrate(m)
        update.commit()
    what = (f"indexed {len(m.index)} nodes with {m.index.vocabulary.size} visual words" if m.index is not None
            else f"{map_path}: too few features for a bag of words; whole-image descriptors refreshed")
    console.print(what)
    if not no_calibration:
        console.print(f"calibration: {_calibration_line(m, map_path)}" if cal is not None else
                      f"calibration: none fitted ({len(m.nodes)} nodes, "
                      f"{sum(n.image is not None for n in m.nodes.values())} keyframe images; see the log)")


@app.command()
def upgrade(map_path: Path = typer.Argument(..., metavar="MAP", help="Map file.")) -> None:
    """Rewrite a map written by an older topomap in the current map schema (atomically).

    Older maps open without it too (migrated in memory, the file untouched); the first command that
    writes to an old map upgrades it as well."""
    old, new = upgrade_map(map_path)
    if old == new:
        console.print(f"{map_path} already uses map schema {new}; nothing to do")
    else:
        console.print(f"upgraded {map_path} from map schema {old} to {new}")
