"""A teach run of the default world builds (topomap build) into a map whose loop is closed."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from topomap.camera import load_camera
from topomap.config import BuildConfig, CalibrationConfig


@pytest.mark.slow
def test_default_world_loop_builds_into_a_closed_loop(tmp_path, world):
    build = pytest.importorskip("topomap.build")
    from topomap.sim.teach import teach

    run = teach(world, "loop", tmp_path / "loop", spacing_m=0.75)
    # the defaults but the confidence calibration (a third of the build), which adds no edge
    config = BuildConfig(calibration=CalibrationConfig(enabled=False))
    tmap = build.build_map(run.out_dir, config, camera=load_camera(run.camera_path))
    with open(run.poses_path, newline="") as f:
        rows = list(csv.DictReader(f))
    order = {r["image"]: i for i, r in enumerate(rows)}
    xz = {r["image"]: np.array([float(r["x"]), float(r["z"])]) for r in rows}
    n = len(rows)
    loops = [e for e in tmap.edges.values() if e.kind.value == "loop"]
    assert loops
    closing = []
    for e in loops:
        a, b = tmap.nodes[e.a].source, tmap.nodes[e.b].source
        gap = float(np.linalg.norm(xz[a] - xz[b]))
        assert gap < 8.0, (a, b, gap)  # look-alike places never fool the geometric verification
        first, last = sorted((order[a], order[b]))
        if first < 0.1 * n and last > 0.85 * n:
            closing.append(gap)
    assert closing and min(closing) < 1.0  # the end of the lap is joined to its start
    assert len(tmap.components()) == 1
