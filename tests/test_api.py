"""The Python API of issue 2: build_map, load_map, TopoMap (with a networkx view) without the CLI."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import networkx as nx

import topomap

DEMO = Path(__file__).resolve().parents[1] / "datasets" / "demo" / "corridor"


def test_public_names_resolve():
    for name in topomap.__all__:
        assert getattr(topomap, name) is not None, name
    assert "build_map" in dir(topomap)


def test_import_is_light():
    """`import topomap` does not pull OpenCV in: the CLI's --help and error types stay fast."""
    code = "import sys, topomap; print('cv2' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip() == "False"


def test_build_save_load_graph(tmp_path):
    from topomap import BuildConfig, FeatureConfig, TopoMap, build_map, load_map, save_map

    m = build_map(DEMO, BuildConfig(features=FeatureConfig(max_features=500)))
    assert isinstance(m, TopoMap) and 2 <= len(m.nodes) < len(m.frames)
    path = save_map(m, tmp_path / "demo.topomap")
    back = load_map(path)
    g = back.graph
    assert isinstance(g, nx.Graph) and g.number_of_nodes() == len(m.nodes) and nx.is_connected(g)
    assert sorted(g.edges) == sorted(m.edges)
