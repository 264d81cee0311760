"""``topomap localize`` and ``topomap eval``: which node is this image at, and how well does that work."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from topomap.config import LocalizeConfig
from topomap.errors import ConfigError, DatasetError
from topomap.features import detector
from topomap.images import open_sequence
from topomap.localize import DESCRIPTORS, Localizer, SequenceLocalizer
from topomap.store import load_map
from topomap_cli.app import app, console, err_console, print_json


def _localizer(map_path: Path, features: str | None, descriptor: str, top_k: int, min_confidence: float | None):
    m = load_map(map_path)
    if features is not None:
        detector(features)
        if features.lower() != m.feature_kind:
            raise ConfigError(
                f"map {map_path.name} was built with {m.feature_kind} features; query it with --features "
                f"{m.feature_kind} (or leave --features out)"
            )
    cfg = LocalizeConfig(descriptor=descriptor, shortlist_k=top_k)
    if min_confidence is not None:
        cfg = dataclasses.replace(cfg, min_confidence=min_confidence)
    return m, Localizer(m, cfg)


def _run(loc: Localizer, query: Path, sequence: bool, quiet: bool, topic: str | None = None):
    """Localize every readable frame of QUERY; returns ``[(name, Localization)]`` and skipped names."""
    seq = open_sequence(query, topic=topic)
    if seq.kind == "image":  # one image: its reason is the error, not a warning and a summary
        frame = next(iter(seq))
        if frame.image is None:
            raise DatasetError(frame.error or f"{query} is not a readable image")
    filt = SequenceLocalizer(loc) if sequence else None
    out, skipped = [], []
    with Progress(TextColumn("[bold]queries"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=err_console, disable=quiet or len(seq) < 2) as bar:
        task = bar.add_task("q", total=len(seq) or None)
        for frame in seq:
            if frame.image is None:
                skipped.append(frame.name)
                err_console.print(f"[yellow]warning:[/] skipped {frame.name}: {frame.error}")
            else:
                out.append((frame.name, filt.update(frame.image) if filt else loc.localize(frame.image)))
            bar.advance(task)
    if not out:
        raise DatasetError(f"no readable query image in {query}")
    return out, skipped


_TOPIC_HELP = "Image topic of a ROS bag QUERY; omitted: the bag's only one."
_DESCRIPTOR_HELP = "Appearance signal: " + "; ".join(f"{k} = {v}" for k, v in DESCRIPTORS.items()) + "."


@app.command()
def localize(
    map_path: Path = typer.Argument(..., metavar="MAP", help="Map file."),
    query: Path = typer.Argument(..., help="Query image, image folder, video or ROS bag."),
    topic: str = typer.Option(None, "--topic", help=_TOPIC_HELP),
    sequence: bool = typer.Option(False, "--sequence", help="Frames arrive in order: fuse them with the temporal filter."),
    descriptor: str = typer.Option("auto", "--descriptor", help=_DESCRIPTOR_HELP),
    top_k: int = typer.Option(10, "--top-k", help="Candidates verified geometrically per query."),
    features: str = typer.Option(None, "--features", help="Expected feature type (must be the map's)."),
    min_confidence: float = typer.Option(None, "--min-confidence", help="Below this probability the answer is 'unknown' [default 0.9]."),
    as_json: bool = typer.Option(False, "--json", help="Print a JSON list, one entry per query."),
) -> None:
    """Find the map node each query image shows (or say it is not in the map)."""
    m, loc = _localizer(map_path, features, descriptor, top_k, min_confidence)
    t0 = time.perf_counter()
    results, _ = _run(loc, query, sequence, as_json, topic)
    dt = (time.perf_counter() - t0) / len(results)
    frames = {n: [f.source for f in m.frames if f.node == n] for n in m.nodes}
    rows = [
        {"query": name, "node": r.node, "frames": frames[r.node], "confidence": r.confidence,
         "status": r.status.value, "calibrated": r.calibrated, "experience": r.experience, "place": r.place,
         "inliers": r.inliers,
         "candidates": [c.node for c in r.candidates[:5]]}
        for name, r in results
    ]
    if as_json:
        print_json(rows)
        _warn_uncalibrated(loc, map_path)
        return
    t = Table(title=f"{len(rows)} queries against {map_path.name} ({dt * 1000:.0f} ms per query)")
    for col in ("query", "node", "keyframe", "confidence", "status", "inliers"):
        t.add_column(col)
    for r in rows:
        style = "green" if r["status"] == "localized" else "yellow"
        t.add_row(r["query"], str(r["node"]), m.nodes[r["node"]].source, f"{r['confidence']:.2f}",
                  f"[{style}]{r['status']}[/]", str(r["inliers"]))
    console.print(t)
    _warn_uncalibrated(loc, map_path)


def _warn_uncalibrated(loc: Localizer, map_path: Path) -> None:
    """After the results (a failing run keeps its one error line): say when confidences are raw."""
    if loc.calibration is None and loc.config.use_calibration:
        err_console.print(f"[yellow]note:[/] {map_path.name} has no calibration for this descriptor: confidences "
                          f"are raw scores, not probabilities (`topomap index {map_path}` fits one)")


def read_truth(m, query: Path, topic: str | None, ground_truth: str, map_poses: Path | None, radius: float | None,
               tolerance: int):
    """The queries' :class:`~topomap.groundtruth.GroundTruth` from the ``--ground-truth`` options."""
    from topomap.groundtruth import from_poses, read_correspondences, read_poses, same_name

    if ground_truth == "same-name":
        return same_name(open_sequence(query, topic=topic).names or [], m, tolerance)
    gt_path = Path(ground_truth)
    if map_poses is not None or radius is not None:
        if map_poses is None or radius is None:
            raise DatasetError("a poses ground truth needs both --map-poses and --radius")
        return from_poses(read_poses(gt_path), read_poses(map_poses), m, radius)
    return read_correspondences(gt_path, m)


GROUND_TRUTH_HELP = ("Correspondence CSV (query_file,matching_ref_indices|files), 'same-name', or a query poses "
                     "CSV (with --map-poses and --radius).")


@app.command("eval")
def eval_(
    map_path: Path = typer.Argument(..., metavar="MAP", help="Map file."),
    query: Path = typer.Argument(..., help="Query image folder, video or ROS bag."),
    topic: str = typer.Option(None, "--topic", help=_TOPIC_HELP),
    ground_truth: str = typer.Option(..., "--ground-truth", help=GROUND_TRUTH_HELP),
    map_poses: Path = typer.Option(None, "--map-poses", help="Poses CSV of the map's frames (with a poses ground truth)."),
    radius: float = typer.Option(None, "--radius", help="Distance [m] within which a map frame shows the query's place (poses ground truth)."),
    tolerance: int = typer.Option(0, "--tolerance", help="same-name: also accept this many frames before/after."),
    sequence: bool = typer.Option(False, "--sequence", help="Use the temporal filter."),
    descriptor: str = typer.Option("auto", "--descriptor", help=_DESCRIPTOR_HELP),
    top_k: int = typer.Option(10, "--top-k", help="Candidates verified geometrically per query."),
    plot: Path = typer.Option(None, "--plot", help="Write the precision-recall curve to this PNG."),
    as_json: bool = typer.Option(False, "--json", help="Print the metrics as JSON."),
) -> None:
    """Precision-recall, AUC, Recall@1/5/10, recall at 100% precision, declared answers and calibration error."""
    from topomap.evaluate import evaluate, plot_pr

    m, loc = _localizer(map_path, None, descriptor, top_k, None)
    if plot is not None and not plot.parent.exists():
        raise DatasetError(f"folder {plot.parent} does not exist (for --plot)")
    # read the ground truth before the (slow) queries so a wrong file fails at once
    truth = read_truth(m, query, topic, ground_truth, map_poses, radius, tolerance)
    t0 = time.perf_counter()
    results, skipped = _run(loc, query, sequence, as_json, topic)
    seconds = (time.perf_counter() - t0) / len(results)
    res = evaluate(results, truth, m)
    data = {**res.to_dict(), "mode": "sequence" if sequence else "single", "descriptor": loc.mode,
            "ms_per_query": round(seconds * 1000, 2), "skipped": skipped}
    if plot is not None:
        plot_pr(res, plot, label=f"topomap {data['mode']} ({loc.mode})")
    if as_json:
        print_json(data)
        _warn_uncalibrated(loc, map_path)
        return
    t = Table(title=f"{map_path.name}: {res.queries} queries ({data['mode']}, {loc.mode})", show_header=False, box=None)
    for k in ("recall_at_1", "recall_at_5", "recall_at_10", "auc", "recall_at_100_precision", "declared",
              "declared_right", "declared_precision"):
        t.add_row(k.replace("_", " "), f"{data[k]:.3f}")
    t.add_row("expected calibration error", f"{res.ece:.3f}" + ("" if res.calibrated else " (raw confidences)"))
    t.add_row("queries with a match", str(res.queries_with_match))
    t.add_row("time", f"{data['ms_per_query']:.1f} ms per query")
    console.print(t)
    if plot is not None:
        err_console.print(f"wrote {plot}")
    _warn_uncalibrated(loc, map_path)
