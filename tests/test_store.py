"""topomap.store: the SQLite map file — round trips, no pickle, foreign/truncated/newer files,
atomic writes and rolled-back appends, exports."""

from __future__ import annotations

import ast
import json
import shutil
import sqlite3
from pathlib import Path

import cv2
import networkx as nx
import numpy as np
import pytest
from conftest import tamper
from map_synth import FAST, write_out_and_back

import topomap.store as store
from topomap.build import build_map
from topomap.camera import CameraIntrinsics
from topomap.config import BuildConfig, FeatureConfig
from topomap.errors import DatasetError, MapFormatError, NodeNotFoundError
from topomap.features import Features
from topomap.graph import Edge, EdgeKind, FrameRecord, Node, TopoMap
from topomap.store import (
    SCHEMA_VERSION,
    check_writable,
    export_graphml,
    export_json,
    load_map,
    load_node_image,
    save_map,
    update_map,
)

@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """(map, path) of the synthetic out-and-back map saved once for this module."""
    root = tmp_path_factory.mktemp("store")
    write_out_and_back(root / "imgs")
    m = build_map(root / "imgs", FAST)
    return m, save_map(m, root / "walk.topomap")


@pytest.fixture
def copy(built, tmp_path):
    """A private copy of the saved map."""
    return Path(shutil.copy(built[1], tmp_path / "copy.topomap"))


def files_in(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


# ----------------------------------------------------------------------------- round trip
def decode_image(data: bytes, what: str = "") -> np.ndarray:
    """Stored image bytes (JPEG or PNG) as pixels."""
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)


def test_round_trip_preserves_everything(built):
    m, path = built
    assert m.edges_by_kind()["loop"] >= 1  # the fixture really closes loops
    back = load_map(path, images=True)
    assert sorted(back.nodes) == sorted(m.nodes)
    for i, n in m.nodes.items():
        b = back.nodes[i]
        assert (b.id, b.sequence, b.frame_id, b.source) == (n.id, n.sequence, n.frame_id, n.source)
        assert b.features.kind == n.features.kind and b.features.image_size == n.features.image_size
        for name in ("keypoints", "descriptors"):  # bit-exact, same dtype
            x, y = getattr(n.features, name), getattr(b.features, name)
            assert x.dtype == y.dtype and x.tobytes() == y.tobytes()
        # images are JPEG by default: the thumbnail comes back within JPEG error, the keyframe image
        # as the build encoded it
        assert b.thumbnail.shape == n.thumbnail.shape
        assert np.abs(b.thumbnail.astype(int) - n.thumbnail).mean() < 6  # a noise texture: JPEG's worst case
        assert n.image is None and n.image_data[:2] == b"\xff\xd8"  # kept encoded during the build
        np.testing.assert_array_equal(b.image, decode_image(n.image_data, "image"))
        assert b.descriptor.dtype == np.float32 and b.descriptor.tobytes() == n.descriptor.tobytes()
    assert back.edges == m.edges
    assert back.frames == m.frames
    assert back.camera == m.camera and back.config == m.config
    assert back.sequences == json.loads(json.dumps(m.sequences))
    assert back.meta["descriptor"] == m.meta["descriptor"]
    a, b = m.index.to_arrays(), back.index.to_arrays()
    assert a.keys() == b.keys()
    for k in a:
        assert a[k].dtype == b[k].dtype and a[k].tobytes() == b[k].tobytes(), k
    # the restored index answers queries like the original
    q = m.nodes[2].features
    assert back.index.shortlist(q, 3) == m.index.shortlist(q, 3)


def test_load_without_images_and_node_image(built):
    m, path = built
    light = load_map(path)
    assert all(n.image is None for n in light.nodes.values())
    np.testing.assert_array_equal(load_node_image(path, 1), decode_image(m.nodes[1].image_data, "image"))
    with pytest.raises(NodeNotFoundError, match="node 99"):
        load_node_image(path, 99)


def test_png_images_round_trip_exactly_and_jpeg_within_its_error(built, tmp_path):
    m, _ = built
    src = next(iter(m.nodes.values()))
    image = decode_image(src.image_data, "image")
    for fmt, tol in (("png", 0), ("jpeg", 6)):
        cfg = BuildConfig(features=FeatureConfig(max_features=500), image_format=fmt, image_quality=75)
        one = TopoMap(camera=m.camera, config=cfg)
        one.add_node(Node(0, 0, 0, "a.png", src.features, src.thumbnail, image=image))
        path = save_map(one, tmp_path / f"{fmt}.topomap")
        blob = sqlite3.connect(path).execute("SELECT image, thumbnail FROM node").fetchone()
        magic = b"\x89PNG" if fmt == "png" else b"\xff\xd8"
        assert blob[0][:4].startswith(magic) and blob[1][:4].startswith(magic)
        back = load_map(path, images=True).nodes[0]
        assert np.abs(back.image.astype(int) - image).mean() <= tol
        assert np.abs(back.thumbnail.astype(int) - src.thumbnail).mean() <= tol


def test_no_images_stores_no_keyframe_image(tmp_path):
    import dataclasses

    write_out_and_back(tmp_path / "imgs")
    m = build_map(tmp_path / "imgs", dataclasses.replace(FAST, store_images=False))
    path = save_map(m, tmp_path / "m.topomap")
    assert sqlite3.connect(path).execute("SELECT COUNT(*) FROM node WHERE image IS NOT NULL").fetchone() == (0,)
    assert load_node_image(path, 0) is None and all(n.thumbnail is not None for n in load_map(path).nodes.values())


def test_sift_features_round_trip_bit_exact(tmp_path):
    rng = np.random.default_rng(5)
    f = Features(rng.uniform(0, 640, (50, 2)).astype(np.float32), rng.standard_normal((50, 128)).astype(np.float32),
                 "sift", (640, 480))
    m = TopoMap(camera=CameraIntrinsics.default(640, 480),
                config=BuildConfig(features=FeatureConfig(kind="sift"), store_images=False))
    m.add_node(Node(0, 0, 0, "a.png", f, np.zeros((12, 16), np.uint8), pose_gt=(1.0, 2.0, 0.5)))
    m.add_node(Node(1, 0, 1, "b.png", Features.empty("sift", (640, 480)), np.ones((12, 16), np.uint8)))
    m.add_edge(Edge(0, 1, EdgeKind.MANUAL, 0, 0.0))
    m.frames = [FrameRecord(0, 0, 0, "a.png", 0), FrameRecord(1, 0, 1, "b.png", 1), FrameRecord(2, 0, 2, "c.png", None, "unreadable")]
    back = load_map(save_map(m, tmp_path / "s.topomap"), images=True)
    assert back.nodes[0].features.descriptors.tobytes() == f.descriptors.tobytes()
    assert back.nodes[0].pose_gt == (1.0, 2.0, 0.5) and back.nodes[0].image is None
    assert len(back.nodes[1].features) == 0 and back.nodes[1].features.descriptors.shape == (0, 128)
    assert back.frames == m.frames and back.index is None
    assert back.edge(0, 1).kind is EdgeKind.MANUAL


def test_load_does_not_modify_the_file(built):
    _, path = built
    before = (path.read_bytes(), path.stat().st_mtime_ns, files_in(path.parent))
    load_map(path, images=True)
    assert (path.read_bytes(), path.stat().st_mtime_ns, files_in(path.parent)) == before


# ----------------------------------------------------------------------------- no pickle
def test_map_file_holds_no_pickle(built):
    _, path = built
    con = sqlite3.connect(path)
    blobs = 0
    for (table,) in con.execute("SELECT name FROM sqlite_master WHERE type = 'table'"):
        cols = [r[1] for r in con.execute(f"PRAGMA table_info({table})")]
        for row in con.execute(f"SELECT * FROM {table}"):
            for col, value in zip(cols, row):
                if isinstance(value, bytes):
                    blobs += 1
                    assert not value.startswith(b"\x80"), f"{table}.{col} looks like a pickle"
                elif isinstance(value, str) and table == "meta" and col == "value":
                    json.loads(value)  # meta values are JSON
    con.close()
    assert blobs > 30  # thumbnails, images, descriptors, features, index arrays


@pytest.mark.parametrize("module", ["store", "retrieval", "graph", "build"])
def test_map_code_never_uses_pickle(module):
    src = (Path(store.__file__).parent / f"{module}.py").read_text()
    tree = ast.parse(src)
    imported = {a.name.split(".")[0] for node in ast.walk(tree) if isinstance(node, (ast.Import, ast.ImportFrom))
                for a in node.names} | {node.module.split(".")[0] for node in ast.walk(tree)
                                        if isinstance(node, ast.ImportFrom) and node.module}
    assert not imported & {"pickle", "cPickle", "dill", "joblib", "shelve"}
    assert "allow_pickle" not in src and "np.load(" not in src


# ----------------------------------------------------------------------------- bad files
def test_missing_and_folder(tmp_path):
    with pytest.raises(MapFormatError, match="does not exist"):
        load_map(tmp_path / "none.topomap")
    with pytest.raises(MapFormatError, match="is a folder"):
        load_map(tmp_path)


def test_empty_and_foreign_files(tmp_path):
    (tmp_path / "empty.topomap").write_bytes(b"")
    with pytest.raises(MapFormatError, match="empty file"):
        load_map(tmp_path / "empty.topomap")
    ok, png = cv2.imencode(".png", np.zeros((8, 8), np.uint8))
    (tmp_path / "image.png").write_bytes(png.tobytes())
    with pytest.raises(MapFormatError, match="not a topomap map file"):
        load_map(tmp_path / "image.png")
    tamper(tmp_path / "other.db", "CREATE TABLE t (x)", "INSERT INTO t VALUES (1)")
    with pytest.raises(MapFormatError, match="SQLite database but not a topomap map"):
        load_map(tmp_path / "other.db")


def test_truncated_map(copy):
    data = copy.read_bytes()
    copy.write_bytes(data[: len(data) // 2])
    with pytest.raises(MapFormatError, match="damaged|truncated"):
        load_map(copy)
    copy.write_bytes(data[:60])
    with pytest.raises(MapFormatError, match="truncated"):
        load_map(copy)


def test_newer_schema_asks_to_upgrade(copy):
    tamper(copy, f"PRAGMA user_version = {SCHEMA_VERSION + 1}")
    with pytest.raises(MapFormatError, match="newer topomap.*upgrade topomap"):
        load_map(copy)
    tamper(copy, "PRAGMA user_version = 0")
    with pytest.raises(MapFormatError, match="no schema version"):
        load_map(copy)


def test_damaged_content(copy):
    tamper(copy, "UPDATE feature SET keypoints = x'0011' WHERE node_id = 1")
    with pytest.raises(MapFormatError, match="keypoints of node 1 does not decode"):
        load_map(copy)


def test_damaged_header(copy):
    tamper(copy, "UPDATE meta SET value = '{\"fx\": ' WHERE key = 'camera'")
    with pytest.raises(MapFormatError, match="header is not valid JSON"):
        load_map(copy)


def test_wrong_format_name(copy):
    tamper(copy, "UPDATE meta SET value = '\"something-else\"' WHERE key = 'format'")
    with pytest.raises(MapFormatError, match="not a topomap map"):
        load_map(copy)


# ----------------------------------------------------------------------------- writing safely
def test_check_writable(tmp_path):
    with pytest.raises(DatasetError, match="does not exist; create it first"):
        check_writable(tmp_path / "nodir" / "m.topomap")
    with pytest.raises(DatasetError, match="is a folder"):
        check_writable(tmp_path)
    (tmp_path / "m.topomap").write_bytes(b"x")
    with pytest.raises(DatasetError, match="already exists; use --force"):
        check_writable(tmp_path / "m.topomap")
    assert check_writable(tmp_path / "m.topomap", overwrite=True) == tmp_path / "m.topomap"
    with pytest.raises(DatasetError, match="cannot append.*does not exist"):
        check_writable(tmp_path / "new.topomap", append=True)


def test_save_refuses_to_overwrite(built, copy):
    m, _ = built
    before = copy.read_bytes()
    with pytest.raises(DatasetError, match="already exists"):
        save_map(m, copy)
    assert copy.read_bytes() == before
    save_map(m, copy, overwrite=True)
    assert load_map(copy).edges == m.edges


@pytest.mark.parametrize("stage", ["_insert_nodes", "_insert_frames", "_write_meta_and_index"])
def test_interrupted_save_leaves_nothing_behind(built, copy, monkeypatch, stage):
    m, _ = built
    folder = copy.parent
    before = copy.read_bytes()

    def interrupt(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(store, stage, interrupt)
    with pytest.raises(KeyboardInterrupt):
        save_map(m, folder / "new.topomap")
    with pytest.raises(KeyboardInterrupt):
        save_map(m, copy, overwrite=True)
    assert files_in(folder) == ["copy.topomap"]  # no new map, no temporary or journal file
    assert copy.read_bytes() == before


def test_interrupted_update_rolls_back(built, copy, monkeypatch):
    m, _ = built
    before = copy.read_bytes()
    grown = load_map(copy)
    n0, f0 = grown.next_node_id(), len(grown.frames)
    extra = grown.nodes[0]
    grown.add_node(Node(n0, 1, f0, "extra.png", extra.features, extra.thumbnail))
    grown.frames.append(FrameRecord(f0, 1, 0, "extra.png", n0))
    grown.add_edge(Edge(0, n0, EdgeKind.LOOP, 99, 0.5))

    def interrupt(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(store, "_upsert_edges", interrupt)  # after the node and frame rows went in
    with pytest.raises(KeyboardInterrupt):
        update_map(grown, copy, first_new_node=n0, first_new_frame=f0)
    assert copy.read_bytes() == before
    assert files_in(copy.parent) == ["copy.topomap"]
    monkeypatch.undo()
    update_map(grown, copy, first_new_node=n0, first_new_frame=f0)
    back = load_map(copy)
    assert back.next_node_id() == n0 + 1 and back.edge(0, n0).inliers == 99 and back.frames[-1].source == "extra.png"


# ----------------------------------------------------------------------------- export
def test_export_json(built):
    m, _ = built
    data = json.loads(json.dumps(export_json(m)))
    assert data["schema_version"] == SCHEMA_VERSION
    assert len(data["nodes"]) == len(m.nodes) and len(data["edges"]) == len(m.edges)
    for n in data["nodes"]:
        assert {"id", "keyframe", "frames"} <= set(n)
        assert n["keyframe"] == m.nodes[n["id"]].source and n["keyframe"] in n["frames"]
    assert sorted(f for n in data["nodes"] for f in n["frames"]) == sorted(f.source for f in m.frames)
    for e in data["edges"]:
        assert {"source", "target", "kind", "inliers"} <= set(e)
        assert m.edge(e["source"], e["target"]).inliers == e["inliers"]
    assert {e["kind"] for e in data["edges"]} == {"sequential", "loop"}


def test_export_graphml_loads_back(built, tmp_path):
    m, _ = built
    g = nx.read_graphml(export_graphml(m, tmp_path / "g.graphml"), node_type=int)
    assert sorted(g.nodes) == sorted(m.nodes) and g.number_of_edges() == len(m.edges)
    n0 = m.nodes[0]
    assert g.nodes[0]["keyframe"] == n0.source and n0.source in g.nodes[0]["frames"].split(";")
    e = next(iter(m.edges.values()))
    assert g.edges[e.a, e.b]["kind"] == e.kind.value and g.edges[e.a, e.b]["inliers"] == e.inliers
