"""topomap.graph: TopoMap nodes, edges, frames and its networkx view (in memory, no I/O)."""

from __future__ import annotations

import networkx as nx
import numpy as np
import pytest

from topomap.camera import CameraIntrinsics
from topomap.errors import ConfigError, NodeNotFoundError, TopomapError
from topomap.features import Features
from topomap.graph import Edge, EdgeKind, FrameRecord, Node, TopoMap


def feats(n: int, kind: str = "orb") -> Features:
    rng = np.random.default_rng(n)
    return Features(rng.uniform(0, 100, (n, 2)).astype(np.float32), rng.integers(0, 256, (n, 32)).astype(np.uint8),
                    kind, (100, 80))


def node(i: int, seq: int = 0, kind: str = "orb") -> Node:
    return Node(i, seq, frame_id=10 * i, source=f"f{10 * i}.png", features=feats(20 + i, kind),
                thumbnail=np.zeros((8, 10), np.uint8))


@pytest.fixture
def chain():
    """Five nodes 0-1-2-3 in sequence, 4 alone; frames 0..9 two per node, frame 9 skipped."""
    m = TopoMap(camera=CameraIntrinsics.default(100, 80))
    for i in range(5):
        m.add_node(node(i))
    for i in range(3):
        m.add_edge(Edge(i, i + 1, EdgeKind.SEQUENTIAL, 100 - i, 0.5))
    m.frames = [FrameRecord(f, 0, f, f"f{f}.png", f // 2 if f < 9 else None, "ok" if f < 9 else "unreadable")
                for f in range(10)]
    return m


def test_edge_is_undirected_and_typed():
    e = Edge(5, 2, "loop", 40, 0.2, 3.5)
    assert (e.a, e.b, e.key) == (2, 5, (2, 5)) and e.kind is EdgeKind.LOOP
    with pytest.raises(ValueError, match="two different nodes"):
        Edge(3, 3, EdgeKind.LOOP, 1, 0.0)
    with pytest.raises(ValueError):
        Edge(1, 2, "teleport", 1, 0.0)
    assert [k.value for k in EdgeKind] == ["sequential", "loop", "manual"]


def test_access(chain):
    assert chain.node(2).source == "f20.png"
    assert chain.neighbours(1) == [0, 2] and chain.neighbours(4) == []
    assert chain.edge(2, 1) is chain.edge(1, 2) is not None and chain.edge(0, 4) is None
    assert [f.id for f in chain.frames if f.node == 3] == [6, 7]
    assert chain.node_of_frame("f5.png") == 2 and chain.node_of_frame("f9.png") is None
    assert chain.node_of_frame("unknown.png") is None
    assert chain.next_node_id() == 5
    assert chain.working_size == (100, 80) and chain.feature_kind == "orb"


def test_unknown_node_is_a_topomap_error(chain):
    with pytest.raises(NodeNotFoundError, match=r"node 7 is not in this map \(it has 5 nodes: ids 0..4\)") as ei:
        chain.node(7)
    assert isinstance(ei.value, TopomapError)
    with pytest.raises(NodeNotFoundError):
        chain.node("x")
    with pytest.raises(NodeNotFoundError):
        chain.add_edge(Edge(0, 9, EdgeKind.MANUAL, 1, 0.0))
    with pytest.raises(NodeNotFoundError):
        chain.neighbours(11)


def test_mutation_rules(chain):
    with pytest.raises(ValueError, match="exists"):
        chain.add_node(node(1))
    with pytest.raises(ConfigError, match="sift features"):
        chain.add_node(node(9, kind="sift"))
    # loop closure rediscovering a sequential edge keeps it sequential
    kept = chain.add_edge(Edge(0, 1, EdgeKind.LOOP, 500, 0.9))
    assert kept.kind is EdgeKind.SEQUENTIAL and kept.inliers == 100
    # a better loop replaces a weaker one, a weaker one does not
    chain.add_edge(Edge(0, 4, EdgeKind.LOOP, 40, 0.2))
    chain.add_edge(Edge(4, 0, EdgeKind.LOOP, 30, 0.1))
    assert chain.edge(0, 4).inliers == 40
    chain.add_edge(Edge(0, 4, EdgeKind.LOOP, 60, 0.3))
    assert chain.edge(0, 4).inliers == 60


def test_graph_view_and_summary(chain):
    g = chain.graph
    assert isinstance(g, nx.Graph) and sorted(g.nodes) == [0, 1, 2, 3, 4]
    assert g.nodes[2]["source"] == "f20.png" and g.nodes[2]["features"] == 22
    assert g.edges[1, 2] == {"kind": "sequential", "inliers": 99, "similarity": 0.5, "flow_px": 0.0}
    assert chain.components() == [[0, 1, 2, 3], [4]]
    chain.add_edge(Edge(3, 4, EdgeKind.MANUAL, 20, 0.1))
    assert chain.components() == [[0, 1, 2, 3, 4]]
    assert chain.edges_by_kind() == {"sequential": 3, "loop": 0, "manual": 1}
    s = chain.summary()
    assert s["nodes"] == 5 and s["frames"] == 10 and s["frames_skipped"] == 1 and s["edges"] == 4
    assert s["components"] == 1 and s["features"] == {"kind": "orb", "total": 110, "per_node_mean": 22.0}
    assert s["camera"]["source"] == "default" and s["index"] is False


def test_empty_map_summary():
    s = TopoMap(camera=CameraIntrinsics.default(10, 10)).summary()
    assert s["nodes"] == 0 and s["components"] == 0 and s["features"]["total"] == 0
