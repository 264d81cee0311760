"""Keyframe-pair geometry stored on the edges (topomap.relative_motion): computed at build time, kept
by the map file, read by the navigator, recomputed when missing, stale or malformed."""

from __future__ import annotations

import dataclasses
import math

import pytest
from map_synth import FAST, SHORT_WALK_PX, write_out_and_back

from topomap.build import build_map
from topomap.config import RelativePoseConfig
from topomap.relative_motion import META_KEY, KeyframePairs, PairMotion, annotate_edges, pair_motion
from topomap.store import load_map, save_map


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    """The short out-and-back walk (sequential and loop edges; each edge's geometry is recomputed below)."""
    root = tmp_path_factory.mktemp("motion")
    write_out_and_back(root / "imgs", length_px=SHORT_WALK_PX)
    m = build_map(root / "imgs", FAST)
    return m, save_map(m, root / "walk.topomap")


def test_build_stores_both_directions_of_every_edge(walk):
    m, _ = walk
    assert m.meta[META_KEY]["version"] == 1
    for e in m.edges.values():
        rm = e.relative_motion
        assert set(rm) == {"version", "a_in_b", "b_in_a"}
        for side, (a, b) in (("a_in_b", (e.a, e.b)), ("b_in_a", (e.b, e.a))):
            fresh = pair_motion(m.nodes[a].features, m.nodes[b].features, m.camera, m.config.match, RelativePoseConfig())
            stored = None if rm[side] is None else PairMotion.from_json(rm[side])
            assert (stored is None) == (fresh is None)
            if fresh is not None:  # the same numbers, not merely close ones: navigation stays identical
                assert stored.to_json() == fresh.to_json()


@pytest.mark.slow  # builds one or more maps end to end (~8-30 s)
def test_the_build_verifies_each_edge_once_more_not_twice(tmp_path, monkeypatch):
    """The build's own verification of an edge (keyframing, loop closure) is one of its directions;
    only the other is verified again for the pair's geometry (the records equal fresh ones, above)."""
    import topomap.relative_motion as rm

    calls = []
    real = rm.verify
    monkeypatch.setattr(rm, "verify", lambda *a, **k: calls.append(1) or real(*a, **k))
    write_out_and_back(tmp_path, length_px=SHORT_WALK_PX)
    m = build_map(tmp_path, FAST)
    assert m.edges_by_kind()["loop"] > 0 and len(calls) == len(m.edges)


def test_the_map_file_keeps_them_and_the_navigator_reads_them(walk):
    m, path = walk
    back = load_map(path)
    assert {k: e.relative_motion for k, e in back.edges.items()} == {k: e.relative_motion for k, e in m.edges.items()}
    pairs = KeyframePairs(back, RelativePoseConfig())
    assert pairs.stored
    e = next(iter(back.edges.values()))
    got = pairs.motion(e.b, e.a)
    want = e.relative_motion["b_in_a"]
    assert (got is None and want is None) or got.to_json() == want


def test_missing_stale_or_malformed_records_are_computed(walk, caplog):
    m, path = walk
    m2 = load_map(path)  # a private copy to damage
    e = next(k for k, v in m2.edges.items() if v.relative_motion["a_in_b"] is not None)
    truth = m2.edges[e].relative_motion
    # another relative-pose configuration: nothing stored applies
    assert not KeyframePairs(m2, RelativePoseConfig(ransac_px=2.0)).stored
    # a record of the wrong shape (a hostile or damaged file): computed again, with a warning
    bad = {"version": 1, "a_in_b": {"theta_rad": "x"}, "b_in_a": None}
    m2.edges[e] = dataclasses.replace(m2.edges[e], relative_motion=bad)
    got = KeyframePairs(m2, RelativePoseConfig()).motion(*e)
    assert got.to_json() == truth["a_in_b"] and "malformed relative motion" in caplog.text
    # an edge without a record (older maps, edges added by hand): annotate_edges fills it in
    m2.edges[e] = dataclasses.replace(m2.edges[e], relative_motion=None)
    assert annotate_edges(m2) == 1
    assert m2.edges[e].relative_motion == truth


def test_pair_motion_json_is_validated():
    ok = PairMotion(0.1, (0.2,), 1.0, 2.0).to_json()
    assert PairMotion.from_json(ok) == PairMotion(0.1, (0.2,), 1.0, 2.0)
    assert math.isnan(PairMotion.from_json({**ok, "theta_rad": None}).theta_rad)
    for bad in ({**ok, "rho_depth_s": None}, {**ok, "wall_normals_rad": "0.1"}, {**ok, "theta_rad": True},
                {**ok, "extra": 1}, {**ok, "rho_depth_s": -1.0}, [1, 2]):
        with pytest.raises(ValueError):
            PairMotion.from_json(bad)


def test_goal_view_gathers_the_neighbours(walk):
    m, _ = walk
    pairs = KeyframePairs(m, RelativePoseConfig())
    node = sorted(m.nodes)[2]
    normals, scale = pairs.goal_view(node, None, 3.0)
    assert scale is None  # no camera height, no metric scale
    assert all(isinstance(n, float) for n in normals)
    normals_h, scale_h = pairs.goal_view(node, 0.7, 3.0)
    assert normals_h == normals
    assert scale_h is None or 1.0 <= scale_h <= 9.0  # clipped to 1/3..3 times the nominal scale
