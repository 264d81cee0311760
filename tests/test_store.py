"""topomap.store: the SQLite map file — round trips, no pickle, foreign/truncated/newer files,
atomic writes and rolled-back appends, exports."""

from __future__ import annotations

import ast
import json
import os
import shutil
import signal
import sqlite3
import time
from pathlib import Path

import cv2
import networkx as nx
import numpy as np
import pytest
from conftest import tamper
from fuzz_cases import map_signature as map_sig
from fuzz_cases import reseal
from map_synth import FAST, SHORT_WALK_PX, write_out_and_back

import topomap.store as store
from topomap.build import build_map
from topomap.camera import CameraIntrinsics
from topomap.config import BuildConfig, FeatureConfig
from topomap.errors import DatasetError, MapFormatError, NodeNotFoundError
from topomap.features import Features
from topomap.graph import Edge, EdgeKind, FrameRecord, Node, TopoMap
from topomap.spill import as_bytes
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
    """(map, path) of the short synthetic out-and-back map (loop closures included) saved once for this module."""
    root = tmp_path_factory.mktemp("store")
    write_out_and_back(root / "imgs", length_px=SHORT_WALK_PX)
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
        assert n.image is None and as_bytes(n.image_data)[:2] == b"\xff\xd8"  # kept encoded during the build
        np.testing.assert_array_equal(b.image, decode_image(as_bytes(n.image_data), "image"))
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
    np.testing.assert_array_equal(load_node_image(path, 1), decode_image(as_bytes(m.nodes[1].image_data), "image"))
    with pytest.raises(NodeNotFoundError, match="node 99"):
        load_node_image(path, 99)


def test_png_images_round_trip_exactly_and_jpeg_within_its_error(built, tmp_path):
    m, _ = built
    src = next(iter(m.nodes.values()))
    image = decode_image(as_bytes(src.image_data), "image")
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


@pytest.mark.slow  # builds one or more maps end to end (~8-30 s)
def test_no_images_stores_no_keyframe_image(tmp_path):
    import dataclasses

    write_out_and_back(tmp_path / "imgs", length_px=SHORT_WALK_PX)
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
    with pytest.raises(MapFormatError, match="row 1 of table feature fails its checksum"):
        load_map(copy)
    reseal(copy)  # an attacker who recomputes the checksums meets the checks behind them
    with pytest.raises(MapFormatError, match="keypoints of node 1 holds 2 bytes"):
        load_map(copy)


def test_damaged_header(copy):
    tamper(copy, "UPDATE meta SET value = '{\"fx\": ' WHERE key = 'camera'")
    with pytest.raises(MapFormatError, match="row camera of table meta fails its checksum"):
        load_map(copy)
    reseal(copy)
    with pytest.raises(MapFormatError, match="header entry 'camera' is not valid JSON"):
        load_map(copy)


def test_wrong_format_name(copy):
    tamper(copy, "UPDATE meta SET value = '\"something-else\"' WHERE key = 'format'")
    reseal(copy)
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
    with pytest.raises(DatasetError, match="does not exist; build it first"):
        check_writable(tmp_path / "new.topomap", append=True)


def test_save_refuses_to_overwrite(built, copy):
    m, _ = built
    before = copy.read_bytes()
    with pytest.raises(DatasetError, match="already exists"):
        save_map(m, copy)
    assert copy.read_bytes() == before
    save_map(m, copy, overwrite=True)
    assert load_map(copy).edges == m.edges


@pytest.mark.parametrize("stage", ["_node_rows", "_frame_rows", "_write_meta_and_arrays"])
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
    grown.sequences.append({"source": "extra"})
    grown.add_node(Node(n0, 1, f0, "extra.png", extra.features, extra.thumbnail))
    grown.frames.append(FrameRecord(f0, 1, 0, "extra.png", n0))
    grown.add_edge(Edge(0, n0, EdgeKind.LOOP, 99, 0.5))

    def interrupt(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(store, "_edge_rows", interrupt)  # after the node and frame rows went in
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


# ----------------------------------------------------------------------------- the validating reader
def test_views_triggers_and_extra_tables_are_refused(copy):
    tamper(copy, "CREATE TRIGGER t AFTER INSERT ON node BEGIN DELETE FROM edge; END")
    with pytest.raises(MapFormatError, match="holds a trigger 't' that topomap never writes.*rebuild"):
        load_map(copy)


def test_recursive_view_is_refused_before_any_query(copy):
    tamper(copy, "ALTER TABLE frame RENAME TO frame_old",
           "CREATE VIEW frame AS WITH RECURSIVE c(x) AS (SELECT 0 UNION ALL SELECT x + 1 FROM c) "
           "SELECT x AS id, 0 AS sequence, x AS seq_index, 'a' AS source, NULL AS node_id, 'ok' AS status, 0 AS crc FROM c")
    with pytest.raises(MapFormatError, match="holds a view 'frame'"):
        load_map(copy)


def test_checksums_cover_every_table(copy):
    for sql in ("UPDATE node SET source = 'x.png' WHERE id = 0", "UPDATE edge SET inliers = inliers + 1",
                "UPDATE frame SET seq_index = seq_index + 1 WHERE id = 0", "UPDATE array SET shape = shape WHERE 0",
                "UPDATE meta SET value = '[]' WHERE key = 'sequences'"):
        c = Path(shutil.copy(copy, copy.with_name("c.topomap")))
        tamper(c, sql)
        if "WHERE 0" in sql:
            load_map(c)  # nothing changed: still fine
            continue
        with pytest.raises(MapFormatError, match="fails its checksum"):
            load_map(c)
    data = load_map(copy, images=True)
    con = sqlite3.connect(copy)
    image = bytearray(con.execute("SELECT image FROM node WHERE id = 1").fetchone()[0])
    image[len(image) // 2] ^= 0x40
    con.execute("UPDATE node SET image = ? WHERE id = 1", (bytes(image),))
    con.commit()
    con.close()
    load_map(copy)  # the image is read on demand only...
    with pytest.raises(MapFormatError, match="image of node 1 fails its checksum"):
        load_map(copy, images=True)  # ... and checked then
    with pytest.raises(MapFormatError, match="image of node 1 fails its checksum"):
        load_node_image(copy, 1)
    assert data.nodes[1].image is not None


def test_lost_rows_are_noticed(copy):
    tamper(copy, "DELETE FROM frame WHERE id = (SELECT max(id) FROM frame)")  # every row left is intact
    with pytest.raises(MapFormatError, match="frame table holds .* rows, the header says"):
        load_map(copy)


def test_other_modules_meta_keys_and_named_arrays_round_trip(built, tmp_path):
    m, path = built
    m2 = load_map(path)
    m2.meta["calibration"] = {"model": "logistic", "a": 1.5, "b": -0.25}
    m2.meta["experiences"] = [{"name": "winter", "nodes": [1, 2]}]
    m2.arrays["calibration_table"] = np.linspace(0, 1, 11, dtype=np.float32)
    p = save_map(m2, tmp_path / "ext.topomap")
    back = load_map(p)
    assert back.meta["calibration"] == m2.meta["calibration"] and back.meta["experiences"] == m2.meta["experiences"]
    np.testing.assert_array_equal(back.arrays["calibration_table"], m2.arrays["calibration_table"])
    with store.open_for_update(p) as u:  # a write by this module keeps what others stored
        u.commit()
    again = load_map(p)
    assert again.meta["calibration"] == m2.meta["calibration"] and "calibration_table" in again.arrays
    m2.arrays["bow_x"] = np.zeros(2)
    with pytest.raises(store.TopomapError, match="reserved"):
        save_map(m2, tmp_path / "clash.topomap")


def test_unknown_array_is_validated(copy):
    tamper(copy, "INSERT INTO array (name, dtype, shape, data, crc) VALUES ('calib', '<f8', '[3]', x'00', 0)")
    reseal(copy)
    with pytest.raises(MapFormatError, match="array 'calib' holds 1 bytes, its shape \\[3\\] needs 24"):
        load_map(copy)


def test_relative_motion_is_json_or_null(copy):
    tamper(copy, "UPDATE edge SET relative_motion = '{\"x_m\": 0.5, \"theta_rad\": 0.1}' WHERE a = 0")
    reseal(copy)
    load_map(copy)  # a JSON object: accepted (issue 13's code interprets it)
    tamper(copy, "UPDATE edge SET relative_motion = '{\"x_m\": ' WHERE a = 0")
    reseal(copy)
    with pytest.raises(MapFormatError, match="relative motion of edge 0-1 is not valid JSON"):
        load_map(copy)


def test_non_utf8_file_names_are_stored_escaped(built, tmp_path):
    m, _ = built
    m2 = load_map(save_map(m, tmp_path / "a.topomap"))
    m2.frames[0] = FrameRecord(0, m2.frames[0].sequence, 0, "caf\udce9.png", m2.frames[0].node, "ok")
    back = load_map(save_map(m2, tmp_path / "b.topomap"))
    assert back.frames[0].source == "caf\\xe9.png"


# ----------------------------------------------------------------------------- writers, locks, crashes
def test_a_second_writer_waits_then_is_refused(copy):
    with store.open_for_update(copy) as u:
        t0 = time.perf_counter()
        with pytest.raises(store.MapConflictError, match="being written by another topomap command"):
            with store.open_for_update(copy, timeout_s=0.3):
                pass
        assert time.perf_counter() - t0 < 5
        load_map(copy)  # readers are not blocked by a writer that has not committed yet
        u.commit()
    with store.open_for_update(copy, timeout_s=0.3) as u:  # released: the next writer goes ahead
        u.commit()


def test_update_map_refuses_a_map_that_changed_since_it_was_loaded(copy):
    a, b = load_map(copy), load_map(copy)
    for m, tag in ((a, "first"), (b, "second")):
        m.sequences.append({"source": tag})
    update_map(a, copy, first_new_node=a.next_node_id(), first_new_frame=len(a.frames))
    with pytest.raises(store.MapConflictError, match="changed since it was loaded"):
        update_map(b, copy, first_new_node=b.next_node_id(), first_new_frame=len(b.frames))
    assert [s.get("source") for s in load_map(copy).sequences][-1] == "first"


def _die_mid_commit(path: Path) -> None:
    """In a forked child: an update whose pages reach the file (tiny cache), killed before COMMIT."""
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child
        try:
            configure = store._configure
            store._configure = lambda con, *, readonly: (configure(con, readonly=readonly), con.execute("PRAGMA cache_size = 2"))
            store._write_meta_and_arrays = lambda *a, **k: os.kill(os.getpid(), signal.SIGKILL)
            with store.open_for_update(path) as u:
                u.map.sequences.append({"source": "killed"})
                extra = u.map.nodes[0]
                for i in range(3):
                    u.map.add_node(Node(u.map.next_node_id(), 1, len(u.map.frames), f"k{i}.png", extra.features, extra.thumbnail, extra.image))
                u.commit()
        finally:
            os._exit(3)
    _, status = os.waitpid(pid, 0)
    assert os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGKILL


@pytest.mark.skipif(not hasattr(os, "fork"), reason="fork")
def test_hot_journal_of_a_killed_writer_is_rolled_back_without_user_action(built, copy):
    before = map_sig(load_map(copy, images=True))
    _die_mid_commit(copy)
    journal = copy.with_name(copy.name + "-journal")
    assert journal.exists() and journal.stat().st_size > 0  # a hot journal, as kill -9 leaves it
    assert map_sig(load_map(copy, images=True)) == before  # rolled back on the next read
    assert not journal.exists()
    with store.open_for_update(copy) as u:  # and the next writer works
        u.map.sequences.append({"source": "next"})
        u.commit()
    assert load_map(copy).sequences[-1] == {"source": "next"}


@pytest.mark.skipif(not hasattr(os, "fork"), reason="fork")
def test_hot_journal_of_a_read_only_map_is_recovered_in_a_private_copy(copy, monkeypatch):
    before = map_sig(load_map(copy, images=True))
    _die_mid_commit(copy)
    monkeypatch.setattr(store.os, "access", lambda p, mode: mode != os.W_OK)  # as for a read-only folder
    listing, data = files_in(copy.parent), copy.read_bytes()
    assert map_sig(load_map(copy, images=True)) == before
    assert files_in(copy.parent) == listing and copy.read_bytes() == data  # nothing written beside it
    with pytest.raises(DatasetError, match="read-only"):
        check_writable(copy, append=True)


def test_a_wal_mode_map_is_read_without_leaving_files(copy):
    con = sqlite3.connect(copy)
    con.execute("PRAGMA journal_mode = WAL")
    con.close()
    listing = files_in(copy.parent)
    assert listing == ["copy.topomap"]
    before = map_sig(load_map(copy, images=True))
    assert files_in(copy.parent) == listing
    writer = sqlite3.connect(copy)  # a WAL holding a commit that is not in the main file yet
    writer.execute("PRAGMA wal_autocheckpoint = 0")
    writer.execute("UPDATE node SET source = source WHERE id = 0")
    writer.commit()
    listing = files_in(copy.parent)
    assert map_sig(load_map(copy, images=True)) == before
    assert files_in(copy.parent) == listing
    writer.close()


def test_leftover_temporary_files_of_dead_processes_are_removed(copy, monkeypatch):
    old = time.time() - 3600
    dead = [copy.with_name(f".{copy.name}.999999.tmp"), copy.with_name(f".{copy.name}.999999.a1b2c3.tmp-journal")]
    mine = copy.with_name(f".{copy.name}.{os.getpid()}.tmp")
    recent = copy.with_name(f".{copy.name}.999998.tmp")
    for p in (*dead, mine, recent):
        p.write_bytes(b"x")
    for p in (*dead, mine):
        os.utime(p, (old, old))
    monkeypatch.setattr(store, "_pid_alive", lambda pid: pid == os.getpid())
    load_map(copy)
    assert not any(p.exists() for p in dead) and mine.exists() and recent.exists()


def test_an_orphan_journal_never_reaches_a_new_map(built, tmp_path):
    m, _ = built
    target = tmp_path / "new.topomap"
    target.with_name("new.topomap-journal").write_bytes(os.urandom(4096))
    save_map(m, target)
    assert files_in(tmp_path) == ["new.topomap"]
    assert load_map(target).edges == m.edges


def test_replacing_a_map_being_written_is_refused(built, copy, monkeypatch):
    m, _ = built
    monkeypatch.setattr(store, "LOCK_TIMEOUT_S", 0.3)
    before = copy.read_bytes()
    with store.open_for_update(copy):
        with pytest.raises(store.MapConflictError):
            save_map(m, copy, overwrite=True)
    assert copy.read_bytes() == before and files_in(copy.parent) == ["copy.topomap"]


def test_object_arrays_are_never_stored(built, tmp_path):
    m, path = built
    m2 = load_map(path)
    m2.arrays["objects"] = np.array([{"a": 1}, None], dtype=object)
    with pytest.raises(store.TopomapError, match="only numbers and booleans"):
        save_map(m2, tmp_path / "o.topomap")
    assert not (tmp_path / "o.topomap").exists() and files_in(tmp_path) == []
