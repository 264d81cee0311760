"""topomap.viz.plots: the map drawing (graph with thumbnails; ground-truth layout when given)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from map_synth import FAST, SHORT_WALK_PX, out_and_back_x, write_out_and_back

from topomap.build import build_map
from topomap.camera import CameraIntrinsics
from topomap.graph import EdgeKind, TopoMap
from topomap.viz import EDGE_STYLE, plot_map
from topomap.viz.plots import _layout


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    """The short out-and-back walk: a graph with sequential and loop edges to draw."""
    folder = tmp_path_factory.mktemp("vizwalk")
    write_out_and_back(folder, length_px=SHORT_WALK_PX)
    return build_map(folder, FAST)


def read_png(path) -> np.ndarray:
    img = cv2.imread(str(path))
    assert img is not None, f"{path} is not a readable PNG"
    return img


def test_plot_map_writes_a_png(walk, tmp_path):
    out = plot_map(walk, tmp_path / "g.png")
    img = read_png(out)
    assert img.shape[0] > 400 and img.shape[1] > 400
    assert img.std() > 5  # something was drawn


def test_plot_uses_ground_truth_positions(walk, tmp_path):
    xs = out_and_back_x(length_px=SHORT_WALK_PX)
    positions = {f"img{i}.png": np.array([x / 100.0, 0.1 * (i % 3)]) for i, x in enumerate(xs)}
    pos, metric = _layout(walk, positions)
    assert metric and all(np.array_equal(pos[n.id], positions[n.source]) for n in walk.nodes.values())
    read_png(plot_map(walk, tmp_path / "gt.png", positions, title="walk"))
    partial = {k: v for k, v in list(positions.items())[:2]}
    assert _layout(walk, partial)[1] is False  # missing positions: falls back to a graph layout


def test_loop_edges_are_drawn_distinctly():
    assert EDGE_STYLE[EdgeKind.LOOP] != EDGE_STYLE[EdgeKind.SEQUENTIAL]
    assert set(EDGE_STYLE) == set(EdgeKind)


def test_plot_trivial_maps(walk, tmp_path):
    one = TopoMap(camera=walk.camera, config=walk.config)
    one.add_node(walk.nodes[0])
    read_png(plot_map(one, tmp_path / "one.png"))
    read_png(plot_map(TopoMap(camera=CameraIntrinsics.default(10, 10)), tmp_path / "empty.png"))
