"""The map file: one SQLite database, versioned, transactional, no pickle.

Writing a new map goes to a temporary file beside the target that replaces it atomically only once
complete, so an interrupted or failed build never leaves half a map and never damages an existing
file. ``--append`` adds rows to an existing map inside one transaction: an interrupted append rolls
back. The rollback journal is used rather than WAL because a read-only WAL reader leaves ``-wal`` and
``-shm`` files beside the map; writes are short (a build computes everything in memory first), and
readers wait for a commit through SQLite's busy timeout.

Arrays are stored as raw little-endian bytes with their dtype and shape in columns and read back
with ``np.frombuffer``; images are PNG. A file is recognised by SQLite's ``application_id``
header field and ``meta.format``; ``PRAGMA user_version`` and ``meta.schema_version`` carry the
schema version. Newer files are refused with an "upgrade topomap" message.
"""

from __future__ import annotations

import json
import logging
import os
import sqlite3
import time
from collections.abc import Iterable
from contextlib import closing
from pathlib import Path

import cv2
import numpy as np

from topomap import __version__
from topomap.camera import CameraIntrinsics
from topomap.config import BuildConfig, from_dict, to_dict
from topomap.errors import ConfigError, DatasetError, MapFormatError, TopomapError
from topomap.features import Features, detector
from topomap.graph import Edge, EdgeKind, FrameRecord, Node, TopoMap

__all__ = ["SCHEMA_VERSION", "FORMAT_NAME", "save_map", "load_map", "update_map", "load_node_image", "check_writable", "export_json", "export_graphml"]

log = logging.getLogger(__name__)

FORMAT_NAME = "topomap-map"
SCHEMA_VERSION = 1
APPLICATION_ID = 0x544F504F  # "TOPO" in the SQLite header: identifies a map without reading tables
_SQLITE_MAGIC = b"SQLite format 3\x00"

SCHEMA = f"""
PRAGMA application_id = {APPLICATION_ID};
PRAGMA user_version = {SCHEMA_VERSION};
CREATE TABLE meta (
    key   TEXT PRIMARY KEY,
    value TEXT NOT NULL            -- JSON
);
CREATE TABLE node (
    id          INTEGER PRIMARY KEY,
    sequence    INTEGER NOT NULL,  -- build run that created it: 0 = first build, 1 = first --append, ...
    frame_id    INTEGER NOT NULL,  -- frame.id of the keyframe image
    source      TEXT NOT NULL,     -- file name of the keyframe image
    width       INTEGER NOT NULL,  -- working resolution the keypoints refer to [px]
    height      INTEGER NOT NULL,
    thumbnail   BLOB NOT NULL,     -- PNG, longest side build_config.thumbnail_px
    image       BLOB,              -- PNG keyframe at the working resolution (NULL: not stored)
    descriptor  BLOB,              -- whole-image descriptor, raw array (see descriptor_dtype/shape)
    descriptor_dtype TEXT,
    descriptor_shape TEXT,
    pose_gt     TEXT               -- JSON ground-truth pose, for plots/scoring only; NULL usually
);
CREATE TABLE feature (
    node_id     INTEGER PRIMARY KEY REFERENCES node(id),
    kind        TEXT NOT NULL,     -- orb | sift | akaze
    count       INTEGER NOT NULL,
    keypoints   BLOB NOT NULL,     -- (count, 2) float32 x, y [px]
    kp_dtype    TEXT NOT NULL,
    descriptors BLOB NOT NULL,     -- (count, D) uint8 (binary) or float32
    desc_dtype  TEXT NOT NULL,
    desc_shape  TEXT NOT NULL      -- JSON [count, D]
);
CREATE TABLE edge (
    a           INTEGER NOT NULL REFERENCES node(id),  -- a < b
    b           INTEGER NOT NULL REFERENCES node(id),
    -- sequential: consecutive keyframes of one sequence;
    -- loop: non-consecutive nodes recognised as the same place (loop closure, --append links);
    -- manual: added by a user
    kind        TEXT NOT NULL CHECK (kind IN ('sequential', 'loop', 'manual')),
    inliers     INTEGER NOT NULL,  -- geometrically verified matches between the two keyframes
    similarity  REAL NOT NULL,     -- inliers / features of the smaller keyframe, 0..1
    flow_px     REAL NOT NULL,     -- median image motion of the inliers [px]
    relative_motion TEXT,          -- JSON, reserved for a reconstructed relative pose; NULL now
    PRIMARY KEY (a, b)
);
CREATE TABLE frame (
    id          INTEGER PRIMARY KEY,
    sequence    INTEGER NOT NULL,
    seq_index   INTEGER NOT NULL,  -- position within its sequence
    source      TEXT NOT NULL,     -- file name (frame_000123 for videos)
    node_id     INTEGER REFERENCES node(id),  -- node representing this frame; NULL if skipped
    status      TEXT NOT NULL      -- ok | unreadable | too small (then node_id is NULL)
);
CREATE INDEX frame_node ON frame(node_id);
CREATE TABLE array (               -- named arrays: the place-recognition index (vocabulary, BoW)
    name        TEXT PRIMARY KEY,
    dtype       TEXT NOT NULL,
    shape       TEXT NOT NULL,     -- JSON
    data        BLOB NOT NULL
);
"""


# ---------------------------------------------------------------------- array and image codecs
def _pack(arr: np.ndarray) -> tuple[bytes, str, str]:
    a = np.ascontiguousarray(arr)
    dt = a.dtype.newbyteorder("<") if a.dtype.byteorder not in ("|", "<") else a.dtype
    a = a.astype(dt, copy=False)
    return a.tobytes(), dt.str, json.dumps(list(a.shape))


def _unpack(data: bytes | None, dtype: str, shape: str, what: str) -> np.ndarray:
    try:
        dt = np.dtype(dtype)
        shp = tuple(int(s) for s in json.loads(shape))
        if dt.hasobject:
            raise ValueError("object arrays are not allowed")
        expected = int(np.prod(shp)) * dt.itemsize
        if data is None or len(data) != expected:
            raise ValueError(f"{0 if data is None else len(data)} bytes, expected {expected}")
        return np.frombuffer(data, dtype=dt).reshape(shp).copy()
    except (TypeError, ValueError, json.JSONDecodeError) as e:
        raise MapFormatError(f"map is damaged: {what} does not decode ({e})") from None


def _png(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    if not ok:  # pragma: no cover - OpenCV encodes any uint8 array
        raise TopomapError("could not encode an image as PNG")
    return buf.tobytes()


def _unpng(data: bytes | None, what: str) -> np.ndarray | None:
    if data is None:
        return None
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise MapFormatError(f"map is damaged: {what} is not a valid PNG")
    return img


# ---------------------------------------------------------------------- checks
def check_writable(path: str | Path, *, overwrite: bool = False, append: bool = False) -> Path:
    """Validate a map output path before any work is done (clear one-line errors)."""
    path = Path(path)
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.exists():
        raise DatasetError(f"folder {parent} does not exist; create it first or choose another -o path")
    if not parent.is_dir():
        raise DatasetError(f"{parent} is not a folder")
    if path.is_dir():
        raise DatasetError(f"{path} is a folder; give a file name such as {path / 'map.topomap'}")
    if append:
        if not path.exists():
            raise DatasetError(f"cannot append: map {path} does not exist; build it first without --append")
        if not os.access(path, os.W_OK) or not os.access(parent, os.W_OK):
            raise DatasetError(f"cannot append: {path} is not writable")
        return path
    if path.exists() and not overwrite:
        raise DatasetError(f"{path} already exists; use --force to overwrite it or --append to add this sequence to it")
    if not os.access(parent, os.W_OK):
        raise DatasetError(f"folder {parent} is not writable")
    return path


def _connect_ro(path: Path) -> sqlite3.Connection:
    """Open read-only, after checking that the file is an SQLite topomap map of a readable version."""
    if not path.exists():
        raise MapFormatError(f"map {path} does not exist; build one with `topomap build SOURCE -o {path.name}`")
    if path.is_dir():
        raise MapFormatError(f"{path} is a folder, not a map file")
    try:
        with open(path, "rb") as fh:
            head = fh.read(100)
    except OSError as e:
        raise MapFormatError(f"cannot read map {path}: {e.strerror or e}") from None
    if len(head) == 0:
        raise MapFormatError(f"{path} is an empty file, not a topomap map")
    if not head.startswith(_SQLITE_MAGIC):
        raise MapFormatError(f"{path} is not a topomap map file (build one with `topomap build`)")
    if len(head) < 100:
        raise MapFormatError(f"map {path} is truncated; rebuild it or restore a copy")
    app_id = int.from_bytes(head[68:72], "big", signed=True)
    if app_id != APPLICATION_ID:
        raise MapFormatError(f"{path} is an SQLite database but not a topomap map")
    uri = f"file:{path.resolve().as_posix()}?mode=ro"
    try:
        con = sqlite3.connect(uri, uri=True, timeout=30)
        version = con.execute("PRAGMA user_version").fetchone()[0]
    except sqlite3.DatabaseError as e:
        raise MapFormatError(f"map {path} is damaged or truncated ({e}); rebuild it or restore a copy") from None
    if version > SCHEMA_VERSION:
        con.close()
        raise MapFormatError(
            f"map {path.name} was written by a newer topomap (map schema {version}, this topomap {__version__} "
            f"reads up to {SCHEMA_VERSION}); upgrade topomap: pip install -U appearance-topomap"
        )
    if version < 1:
        con.close()
        raise MapFormatError(f"map {path} has no schema version; it is not a topomap map")
    return con


# ---------------------------------------------------------------------- writing
def _meta_rows(m: TopoMap) -> dict[str, object]:
    return {
        "format": FORMAT_NAME,
        "schema_version": SCHEMA_VERSION,
        "topomap_version": __version__,
        "created_utc": m.meta.get("created_utc", time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())),
        "modified_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "build_config": to_dict(m.config),
        "camera": m.camera.to_dict(),
        "feature_kind": m.feature_kind,
        "sequences": m.sequences,
        "descriptor": m.meta.get("descriptor"),
        **({"teach_world": m.meta["teach_world"]} if m.meta.get("teach_world") is not None else {}),
    }


def _insert_nodes(con: sqlite3.Connection, nodes: Iterable[Node]) -> None:
    for n in nodes:
        if n.descriptor is not None:
            d_blob, d_dt, d_shape = _pack(n.descriptor)
        else:
            d_blob = d_dt = d_shape = None
        con.execute(
            "INSERT INTO node VALUES (?,?,?,?,?,?,?,?,?,?,?,?)",
            (
                n.id, n.sequence, n.frame_id, n.source, n.features.image_size[0], n.features.image_size[1],
                _png(n.thumbnail), _png(n.image) if n.image is not None else None,
                d_blob, d_dt, d_shape, json.dumps(list(n.pose_gt)) if n.pose_gt is not None else None,
            ),
        )
        kp, kp_dt, _ = _pack(n.features.keypoints.astype(np.float32))
        de, de_dt, de_shape = _pack(n.features.descriptors)
        con.execute(
            "INSERT INTO feature VALUES (?,?,?,?,?,?,?,?)",
            (n.id, n.features.kind, len(n.features), kp, kp_dt, de, de_dt, de_shape),
        )


def _upsert_edges(con: sqlite3.Connection, edges: Iterable[Edge]) -> None:
    con.executemany(
        "INSERT OR REPLACE INTO edge VALUES (?,?,?,?,?,?,NULL)",
        [(e.a, e.b, e.kind.value, e.inliers, e.similarity, e.flow_px) for e in edges],
    )


def _insert_frames(con: sqlite3.Connection, frames: Iterable[FrameRecord]) -> None:
    con.executemany(
        "INSERT INTO frame VALUES (?,?,?,?,?,?)",
        [(f.id, f.sequence, f.index, f.source, f.node, f.status) for f in frames],
    )


def _write_meta_and_index(con: sqlite3.Connection, m: TopoMap) -> None:
    con.executemany("INSERT OR REPLACE INTO meta VALUES (?, ?)", [(k, json.dumps(v)) for k, v in _meta_rows(m).items()])
    con.execute("DELETE FROM array")
    if m.index is not None:
        for name, arr in m.index.to_arrays().items():
            blob, dt, shape = _pack(arr)
            con.execute("INSERT INTO array VALUES (?,?,?,?)", (name, dt, shape, blob))


def save_map(m: TopoMap, path: str | Path, *, overwrite: bool = False) -> Path:
    """Write ``m`` as a new map file; atomic: the target appears (or is replaced) only when complete."""
    path = check_writable(path, overwrite=overwrite)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.unlink(missing_ok=True)
    try:
        with closing(sqlite3.connect(tmp)) as con:
            con.executescript(SCHEMA)
            with con:  # one transaction
                _insert_nodes(con, sorted(m.nodes.values(), key=lambda n: n.id))
                _upsert_edges(con, sorted(m.edges.values(), key=lambda e: e.key))
                _insert_frames(con, m.frames)
                _write_meta_and_index(con, m)
        os.replace(tmp, path)
    except BaseException:
        for leftover in (tmp, tmp.with_name(tmp.name + "-journal")):
            leftover.unlink(missing_ok=True)
        raise
    return path


def update_map(m: TopoMap, path: str | Path, *, first_new_node: int, first_new_frame: int) -> Path:
    """Write the growth of a loaded map back in place, in one transaction (``--append``, ``index``).

    Inserts the nodes and frames from the given ids on, upserts every edge and rewrites the header
    and the index. An interruption rolls the whole update back; the file stays as it was.
    """
    path = check_writable(path, append=True)
    _connect_ro(path).close()  # same identity/version checks as reading
    con = sqlite3.connect(path, timeout=30)
    try:
        con.execute("BEGIN IMMEDIATE")
        _insert_nodes(con, [n for i, n in sorted(m.nodes.items()) if i >= first_new_node])
        _insert_frames(con, [f for f in m.frames if f.id >= first_new_frame])
        _upsert_edges(con, sorted(m.edges.values(), key=lambda e: e.key))
        _write_meta_and_index(con, m)
        con.execute("COMMIT")
    except BaseException:
        if con.in_transaction:
            con.execute("ROLLBACK")
        raise
    finally:
        con.close()
    return path


# ---------------------------------------------------------------------- reading
def load_map(path: str | Path, *, images: bool = False) -> TopoMap:
    """Open a map file. ``images=True`` also decodes the stored keyframe images (slower).

    Raises :class:`MapFormatError` with one clear line for a missing, foreign, truncated, damaged
    or newer-version file. The file is opened read-only and never modified.
    """
    path = Path(path)
    con = _connect_ro(path)
    try:
        with closing(con):
            return _read(con, path, images)
    except sqlite3.DatabaseError as e:
        raise MapFormatError(f"map {path} is damaged or truncated ({e}); rebuild it or restore a copy") from None


def _read(con: sqlite3.Connection, path: Path, images: bool) -> TopoMap:
    try:
        meta = {k: json.loads(v) for k, v in con.execute("SELECT key, value FROM meta")}
    except (TypeError, ValueError):  # json.JSONDecodeError is a ValueError
        raise MapFormatError(f"map {path} is damaged: its header is not valid JSON; rebuild it or restore a copy") from None
    if meta.get("format") != FORMAT_NAME:
        raise MapFormatError(f"{path} is not a topomap map (format {meta.get('format')!r})")
    try:
        config = from_dict(BuildConfig, meta["build_config"])
        camera = CameraIntrinsics.from_dict(meta["camera"])
    except (KeyError, ConfigError, DatasetError) as e:
        raise MapFormatError(f"map {path} has an unreadable header ({e})") from None
    kind = config.features.kind
    detector(kind)  # known feature type
    m = TopoMap(camera=camera, config=config, sequences=list(meta.get("sequences") or []))
    m.meta = {"created_utc": meta.get("created_utc"), "topomap_version": meta.get("topomap_version"),
              "schema_version": SCHEMA_VERSION, "descriptor": meta.get("descriptor")}
    if meta.get("teach_world") is not None:  # the simulator world of the teach run (topomap.build)
        m.meta["teach_world"] = meta["teach_world"]
    feats = {}
    for node_id, fkind, count, kp, kp_dt, de, de_dt, de_shape in con.execute(
        "SELECT node_id, kind, count, keypoints, kp_dtype, descriptors, desc_dtype, desc_shape FROM feature"
    ):
        keypoints = _unpack(kp, kp_dt, json.dumps([count, 2]), f"keypoints of node {node_id}")
        descriptors = _unpack(de, de_dt, de_shape, f"descriptors of node {node_id}")
        feats[node_id] = (fkind, keypoints, descriptors)
    cols = "id, sequence, frame_id, source, width, height, thumbnail, descriptor, descriptor_dtype, descriptor_shape, pose_gt"
    if images:
        cols += ", image"
    for row in con.execute(f"SELECT {cols} FROM node ORDER BY id"):
        nid, seq, frame_id, source, w, h, thumb, d_blob, d_dt, d_shape, pose = row[:11]
        if nid not in feats:
            raise MapFormatError(f"map {path} is damaged: node {nid} has no features")
        fkind, kp, de = feats[nid]
        node = Node(
            id=nid, sequence=seq, frame_id=frame_id, source=source,
            features=Features(kp, de, fkind, (w, h)),
            thumbnail=_unpng(thumb, f"thumbnail of node {nid}"),
            image=_unpng(row[11], f"image of node {nid}") if images else None,
            descriptor=_unpack(d_blob, d_dt, d_shape, f"descriptor of node {nid}") if d_blob is not None else None,
            pose_gt=tuple(json.loads(pose)) if pose else None,
        )
        m.nodes[nid] = node
    for a, b, kind_, inl, sim, flow in con.execute("SELECT a, b, kind, inliers, similarity, flow_px FROM edge ORDER BY a, b"):
        try:
            m.edges[(a, b)] = Edge(a, b, EdgeKind(kind_), inl, sim, flow)
        except ValueError:
            raise MapFormatError(f"map {path} is damaged: edge {a}-{b} has unknown kind {kind_!r}") from None
    m.frames = [
        FrameRecord(i, s, si, src, nid, st)
        for i, s, si, src, nid, st in con.execute("SELECT id, sequence, seq_index, source, node_id, status FROM frame ORDER BY id")
    ]
    arrays = {
        name: _unpack(data, dt, shape, f"index array {name}")
        for name, dt, shape, data in con.execute("SELECT name, dtype, shape, data FROM array")
    }
    if arrays:
        from topomap.retrieval import BowIndex

        m.index = BowIndex.from_arrays(arrays, kind)
    return m


def load_node_image(path: str | Path, node_id: int) -> np.ndarray | None:
    """The stored keyframe image of one node (``None`` if the map does not store images)."""
    path = Path(path)
    with closing(_connect_ro(path)) as con:
        try:
            row = con.execute("SELECT image FROM node WHERE id = ?", (int(node_id),)).fetchone()
        except sqlite3.DatabaseError as e:
            raise MapFormatError(f"map {path} is damaged or truncated ({e})") from None
    if row is None:
        from topomap.errors import NodeNotFoundError

        raise NodeNotFoundError(f"node {node_id} is not in map {path.name}")
    return _unpng(row[0], f"image of node {node_id}")


# ---------------------------------------------------------------------- export
def export_json(m: TopoMap) -> dict:
    """The map as JSON-able data: ``nodes`` (id, keyframe, frames, sequence) and ``edges``."""
    frames_by_node: dict[int, list[str]] = {}
    for f in m.frames:
        if f.node is not None:
            frames_by_node.setdefault(f.node, []).append(f.source)
    return {
        "format": FORMAT_NAME,
        "schema_version": SCHEMA_VERSION,
        "camera": m.camera.to_dict(),
        "nodes": [
            {"id": n.id, "keyframe": n.source, "frames": frames_by_node.get(n.id, []), "sequence": n.sequence,
             "features": len(n.features)}
            for n in sorted(m.nodes.values(), key=lambda n: n.id)
        ],
        "edges": [
            {"source": e.a, "target": e.b, "kind": e.kind.value, "inliers": e.inliers,
             "similarity": round(e.similarity, 6), "flow_px": round(e.flow_px, 3)}
            for e in sorted(m.edges.values(), key=lambda e: e.key)
        ],
    }


def export_graphml(m: TopoMap, path: str | Path) -> Path:
    """GraphML for Gephi/yEd/networkx; a node's frames are joined with ``;`` (GraphML has no lists)."""
    import networkx as nx

    g = m.graph
    frames_by_node: dict[int, list[str]] = {}
    for f in m.frames:
        if f.node is not None:
            frames_by_node.setdefault(f.node, []).append(f.source)
    for n in g.nodes:
        g.nodes[n]["keyframe"] = m.nodes[n].source
        g.nodes[n]["frames"] = ";".join(frames_by_node.get(n, []))
        del g.nodes[n]["source"]
    nx.write_graphml(g, str(path))
    return Path(path)
