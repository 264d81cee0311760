"""topomap.viz.rerun, `topomap navigate --rerun` and `topomap show --rerun`: the .rrd opens with
Rerun's own reader and holds the image, trajectory, graph and scalar streams (issue 18)."""

from __future__ import annotations

import json
import math
import sys
from collections import defaultdict

import numpy as np
import pytest
from conftest import assert_error

pytest.importorskip("rerun", reason="the viz extra (rerun-sdk) is not installed")


def read_rrd(path) -> dict[str, list]:
    """Entity path -> list of (record batch) chunks, read back with Rerun's reader."""
    from rerun.chunk import RrdReader

    store = RrdReader(path).store()
    out = defaultdict(list)
    for chunk in store.stream():
        out[chunk.entity_path].append(chunk.to_record_batch())
    return out


def column(batches, name: str) -> list:
    """The non-null values of one component over an entity's chunks (components may share a chunk)."""
    values = []
    for rb in batches:
        if name in rb.schema.names:
            values += [v for v in rb.column(rb.schema.names.index(name)).to_pylist() if v is not None]
    return values


def rows(batches) -> int:
    return sum(rb.num_rows for rb in batches)


@pytest.fixture(scope="module")
def recording(short_run):
    return read_rrd(short_run["rrd"]), short_run


@pytest.mark.slow  # the short_run fixture drives the simulator (~30 s)
def test_navigation_recording_holds_every_stream(recording):
    rec, run = recording
    moved = round(run["result"]["duration_s"] / 0.1)  # control periods the robot moved
    # images: the camera every step (a subgoal switch is one more step without moving), its matches
    # and flow, the subgoal keyframes
    assert moved <= rows(rec["/camera/image"]) <= moved + run["result"]["subgoals_reached"] + 2
    blobs = column(rec["/camera/image"], "EncodedImage:blob")
    assert all(bytes(b[0][:2]) == b"\xff\xd8" for b in blobs[:3])  # JPEG
    assert rows(rec["/camera/image/matches"]) == rows(rec["/camera/image"])
    assert rows(rec["/subgoal/image"]) >= run["result"]["subgoals_reached"]
    # trajectories over the floor plan: true (simulation), estimated, their trails; walls, map, route
    for entity in ("/world/truth", "/world/estimate", "/world/truth/trail", "/world/estimate/trail", "/world/walls",
                   "/world/map/nodes", "/world/route", "/world/subgoal"):
        assert rows(rec[entity]) >= 1, entity
    assert rows(rec["/world/truth"]) == rows(rec["/camera/image"])
    # the graph: every node and edge of the map
    from topomap.store import load_map

    m = load_map(run["map"])
    nodes = column(rec["/map/graph"], "GraphNodes:node_ids")
    edges = column(rec["/map/graph"], "GraphEdges:edges")
    assert sorted(int(n) for n in nodes[0]) == sorted(m.nodes) and len(edges[0]) == len(m.edges)
    # scalars: servo estimates and commands every step
    for entity in ("/servo/inliers", "/servo/d_omega_rps", "/command/v_f_mps", "/command/omega_rps",
                   "/truth/distance_to_subgoal_m"):
        assert rows(rec[entity]) == rows(rec["/camera/image"]), entity
    dist = [v[0] for v in column(rec["/servo/distance_m"], "Scalars:scalars")]
    assert 0 < len(dist) <= rows(rec["/camera/image"]) and all(math.isfinite(d) and d >= 0 for d in dist)
    # events as a text log, ending with the arrival
    texts = [t[0] for t in column(rec["/events"], "TextLog:text")]
    assert texts[0].startswith("planned") and texts[-1].startswith("arrived")


@pytest.mark.slow  # the short_run fixture drives the simulator (~30 s)
def test_estimated_trajectory_follows_the_true_one(recording):
    """The servo's pose placed at the subgoal keyframe's teach pose lies near the true pose: the
    drawing's frame conventions are right (a sign error would put it metres away)."""
    rec, _ = recording

    def by_step(entity):
        out = {}
        for rb in rec[entity]:
            for s, p in zip(rb.column(rb.schema.names.index("step")).to_pylist(),
                            rb.column(rb.schema.names.index("Points2D:positions")).to_pylist()):
                out[s] = np.array(p[0])
        return out

    est, truth = by_step("/world/estimate"), by_step("/world/truth")
    common = sorted(set(est) & set(truth))
    assert len(common) > 0.8 * len(truth)
    assert float(np.median([np.linalg.norm(est[k] - truth[k]) for k in common])) < 0.15


@pytest.mark.slow  # the short_run fixture drives the simulator (~30 s)
def test_show_writes_the_map_recording(short_run, runner, cli_app, tmp_path):
    from topomap.store import load_map

    out = tmp_path / "map.rrd"
    r = runner.invoke(cli_app, ["show", str(short_run["map"]), "--rerun", str(out), "--poses",
                                str(short_run["teach"] / "poses.csv")])
    assert r.exit_code == 0, r.output
    rec = read_rrd(out)
    m = load_map(short_run["map"])
    assert rows(rec["/map/keyframe"]) == len(m.nodes)
    assert sorted(int(n) for n in column(rec["/map/graph"], "GraphNodes:node_ids")[0]) == sorted(m.nodes)
    assert rows(rec["/world/map/nodes"]) == 1 and rows(rec["/world/map/selected"]) == len(m.nodes)


@pytest.mark.slow  # the short_run fixture drives the simulator (~30 s)
def test_rerun_bad_options_are_one_line(short_run, runner, cli_app, tmp_path, monkeypatch):
    m = str(short_run["map"])
    nav = ["navigate", m, "--goal", "2", "--start-node", "0"]
    assert_error(runner.invoke(cli_app, nav + ["--rerun", str(tmp_path / "run.txt")]), "ends in .rrd")
    assert_error(runner.invoke(cli_app, nav + ["--rerun", str(tmp_path / "no" / "run.rrd")]), "does not exist")
    assert_error(runner.invoke(cli_app, ["show", m]), "-o FILE.png", "--rerun FILE.rrd")
    assert_error(runner.invoke(cli_app, ["show", m, "--rerun", str(tmp_path / "m.png")]), "cannot write m.png", ".rrd")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(sys, "platform", "linux")
    assert_error(runner.invoke(cli_app, nav + ["--rerun-spawn"]), "cannot start a Rerun viewer", "no display")
    assert_error(runner.invoke(cli_app, ["navigate", "--rerun-spawn"]), "no display")  # the demo: before teaching
    monkeypatch.setitem(sys.modules, "rerun", None)
    assert_error(runner.invoke(cli_app, nav + ["--rerun", str(tmp_path / "r.rrd")]), "pip install 'appearance-topomap[viz]'")
    assert not (tmp_path / "r.rrd").exists()


@pytest.mark.slow  # the short_run fixture drives the simulator (~30 s)
def test_logging_changes_nothing_in_the_run(short_run, tmp_path):
    """The logger is a listener, not part of the loop: the same episode with and without it drives
    the very same trajectory (the run is deterministic)."""
    from topomap.groundtruth import read_poses
    from topomap.sim.episode import goal_pose, run_episode
    from topomap.sim.world import load_world
    from topomap.store import load_map
    from topomap.viz.rerun import RerunLogger

    m = load_map(short_run["map"], images=True)
    world = load_world(short_run["teach"] / "world.json")
    poses = read_poses(short_run["teach"] / "poses.csv")
    plain = run_episode(m, world, 2, poses, start_node=0, disturbance="bias")
    logger = RerunLogger(m, tmp_path / "r.rrd", node_poses={n: goal_pose(m, poses, n) for n in m.nodes})
    logged = run_episode(m, world, 2, poses, start_node=0, disturbance="bias", on_event=logger, on_truth=logger.log_truth)
    assert logger.close() == tmp_path / "r.rrd"
    assert np.array_equal(plain.trajectory, logged.trajectory) and plain.to_dict() == logged.to_dict()
    assert rows(read_rrd(tmp_path / "r.rrd")["/camera/image"]) == logger.steps > 0


def test_a_viewer_that_goes_away_loses_nothing(tmp_path, caplog, monkeypatch):
    """A spawned viewer that closes (or cannot start: no usable GPU) fails the flush of its sink:
    the run goes on, the file holds the whole recording, and one warning says so."""
    import logging

    from map_synth import FAST, sequence, write_sequence

    from topomap.build import build_map
    from topomap.viz.rerun import RerunLogger, log_map

    write_sequence(tmp_path / "imgs", sequence(6))
    m = build_map(tmp_path / "imgs", FAST)
    logger = RerunLogger(m, tmp_path / "r.rrd")

    def severed(*a, **k):
        raise RuntimeError("gRPC connection severed: Failed to send messages")

    monkeypatch.setattr(logger.rec, "flush", severed)
    with caplog.at_level(logging.WARNING, logger="topomap"):
        assert logger.close() == tmp_path / "r.rrd"
    assert "viewer stopped receiving" in caplog.text and "r.rrd holds the whole recording" in caplog.text
    rec = read_rrd(tmp_path / "r.rrd")
    assert len(column(rec["/map/graph"], "GraphNodes:node_ids")[0]) == len(m.nodes)
    # the map alone, without positions: graph and one thumbnail per node
    out = log_map(m, tmp_path / "m.rrd")
    rec = read_rrd(out)
    assert rows(rec["/map/keyframe"]) == len(m.nodes) and "/world/map/nodes" not in rec
