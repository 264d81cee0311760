"""The map file: one SQLite database, versioned, validated, transactional, no pickle.

**Writing.** A new map goes to a temporary file beside the target that replaces it atomically only
once complete, so an interrupted or failed build never leaves half a map and never damages an
existing file. Growing a map in place (``build --append``, ``index``) is one read-modify-write under
SQLite's write lock (:func:`open_for_update`): the lock is taken *before* the map is read and held
until the commit, so two writers are serialised (the second waits up to :data:`LOCK_TIMEOUT_S`, then
is refused with one line) and neither can overwrite what the other wrote. :func:`update_map`, for a
map loaded earlier, refuses when the file's ``revision`` moved since it was loaded. An interrupted
update rolls back; the hot journal a killed writer leaves is rolled back by the next command that
opens the map, without user action. The rollback journal is used rather than WAL because a
read-only WAL reader leaves ``-wal`` and ``-shm`` files beside the map.

**Reading** goes through one validating reader: the file must be a regular file with SQLite's
header and topomap's ``application_id``, its ``sqlite_master`` must be exactly the schema topomap
wrote for its version (no views, triggers, virtual tables, extra or missing tables, indexes or
columns), every row is type- and range-checked, and every row carries a CRC-32 that is verified
(schema 2). Any failure is a :class:`MapFormatError` with one line saying what to do. Reading never
writes the file and leaves no files behind (a map in WAL mode is opened immutable, or read from a
temporary copy).

**Schema versions.** Each released schema's definition is kept (:data:`SCHEMAS`). Maps of an older
schema are migrated on open, in memory, and rewritten as the current schema by :func:`upgrade_map`
(``topomap upgrade MAP``) or by the next command that writes them; newer files are refused with an
"upgrade topomap" message. Schema 2 added the ``crc`` column of every table and ``node.image_crc``,
and the ``revision`` / ``row_counts`` header keys.

**Extending the file.** New persisted data goes into ``TopoMap.meta[key]`` (any JSON value; stored
under that key in ``meta`` and read back into ``meta``) or ``TopoMap.arrays[name]`` (named numeric
arrays, stored raw in ``array``), never into new tables or columns. Arrays are raw little-endian
bytes with their dtype and shape in columns, read back with ``np.frombuffer``; images are PNG or
JPEG (``BuildConfig.image_format``) and pass :func:`topomap.images.decode_image`.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import re
import secrets
import shutil
import sqlite3
import stat
import struct
import tempfile
import threading
import time
import zlib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

from topomap import __version__
from topomap.camera import CameraIntrinsics
from topomap.config import BuildConfig, from_dict, to_dict
from topomap.errors import ConfigError, DatasetError, MapConflictError, MapFormatError, TopomapError
from topomap.features import Features, detector
from topomap.graph import Edge, EdgeKind, FrameRecord, Node, TopoMap
from topomap.images import MAX_WORKING_SIDE_PX, decode_image, display_name
from topomap.spill import as_bytes

__all__ = [
    "SCHEMA_VERSION",
    "SCHEMAS",
    "FORMAT_NAME",
    "LOCK_TIMEOUT_S",
    "MapUpdate",
    "save_map",
    "load_map",
    "update_map",
    "open_for_update",
    "upgrade_map",
    "map_schema_version",
    "load_node_image",
    "encode_image",
    "check_writable",
    "export_json",
    "export_graphml",
]

log = logging.getLogger(__name__)

FORMAT_NAME = "topomap-map"
SCHEMA_VERSION = 2
APPLICATION_ID = 0x544F504F  # "TOPO" in the SQLite header: identifies a map without reading tables
_SQLITE_MAGIC = b"SQLite format 3\x00"

#: What SQLite raises on a damaged file (its message about a damaged schema may itself not decode).
_SQLITE_ERRORS = (sqlite3.DatabaseError, UnicodeDecodeError)
#: How long a writer waits for another writer's lock before it is refused [s].
LOCK_TIMEOUT_S = 10.0
#: How long a reader waits for a commit, and a committing writer for readers to finish [s].
BUSY_TIMEOUT_S = 60.0
#: Leftover temporary files of dead processes younger than this are left alone [s].
STALE_TEMP_AGE_S = 60.0

#: Header keys this module writes and checks; any other key is kept as JSON in ``TopoMap.meta``.
_RESERVED_META = frozenset({"format", "schema_version", "topomap_version", "created_utc", "modified_utc",
                            "build_config", "camera", "feature_kind", "sequences", "descriptor", "revision",
                            "row_counts"})
#: Arrays of the place-recognition index (``BowIndex.to_arrays``); other names go to ``TopoMap.arrays``.
_INDEX_ARRAY = re.compile(r"(vocab|bow)_.*")
#: Array dtypes accepted in a map (what ``_pack`` writes: little-endian numbers and booleans).
_ARRAY_DTYPES = frozenset({"|b1", "|i1", "|u1", "<i2", "<u2", "<i4", "<u4", "<i8", "<u8", "<f2", "<f4", "<f8"})
_MAX_JSON_CHARS = 256 << 20
_MAX_TEXT_CHARS = 64 << 10  # file names, statuses, dtype and shape strings
_MAX_FEATURES = 1_000_000
_MAX_ID = 2**31 - 1
_STATUS = re.compile(r"[a-z][a-z _-]{0,63}")  # frame statuses: ok | unreadable | too small | ...

# ---------------------------------------------------------------------- schema definitions
#: Schema 1, as topomap 0.1.0 wrote it (verbatim: files are checked against this exact text).
SCHEMA_V1 = """
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

#: Schema 2: schema 1 plus a CRC-32 per row (``crc``: of every other column, see ``_row_crc``;
#: ``node.image_crc``: of the keyframe image, which is read only on demand).
SCHEMA_V2 = """
CREATE TABLE meta (
    key   TEXT PRIMARY KEY,
    value TEXT NOT NULL,           -- JSON
    crc   INTEGER NOT NULL         -- CRC-32 of the row's other columns (every table has one)
);
CREATE TABLE node (
    id          INTEGER PRIMARY KEY,
    sequence    INTEGER NOT NULL,  -- build run that created it: 0 = first build, 1 = first --append, ...
    frame_id    INTEGER NOT NULL,  -- frame.id of the keyframe image
    source      TEXT NOT NULL,     -- file name of the keyframe image
    width       INTEGER NOT NULL,  -- working resolution the keypoints refer to [px]
    height      INTEGER NOT NULL,
    thumbnail   BLOB NOT NULL,     -- PNG or JPEG, longest side build_config.thumbnail_px
    image       BLOB,              -- PNG or JPEG keyframe at the working resolution (NULL: not stored)
    descriptor  BLOB,              -- whole-image descriptor, raw array (see descriptor_dtype/shape)
    descriptor_dtype TEXT,
    descriptor_shape TEXT,
    pose_gt     TEXT,              -- JSON ground-truth pose, for plots/scoring only; NULL usually
    image_crc   INTEGER,           -- CRC-32 of image (NULL with it); crc covers every column but image
    crc         INTEGER NOT NULL
);
CREATE TABLE feature (
    node_id     INTEGER PRIMARY KEY REFERENCES node(id),
    kind        TEXT NOT NULL,     -- orb | sift | akaze
    count       INTEGER NOT NULL,
    keypoints   BLOB NOT NULL,     -- (count, 2) float32 x, y [px]
    kp_dtype    TEXT NOT NULL,
    descriptors BLOB NOT NULL,     -- (count, D) uint8 (binary) or float32
    desc_dtype  TEXT NOT NULL,
    desc_shape  TEXT NOT NULL,     -- JSON [count, D]
    crc         INTEGER NOT NULL
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
    relative_motion TEXT,          -- JSON object of numbers (keyframe-pair geometry) or NULL
    crc         INTEGER NOT NULL,
    PRIMARY KEY (a, b)
);
CREATE TABLE frame (
    id          INTEGER PRIMARY KEY,  -- 0 .. frames - 1, in input order
    sequence    INTEGER NOT NULL,
    seq_index   INTEGER NOT NULL,  -- position within its sequence
    source      TEXT NOT NULL,     -- file name (frame_000123 for videos)
    node_id     INTEGER REFERENCES node(id),  -- node representing this frame; NULL if skipped
    status      TEXT NOT NULL,     -- ok | unreadable | too small (then node_id is NULL)
    crc         INTEGER NOT NULL
);
CREATE INDEX frame_node ON frame(node_id);
CREATE TABLE array (               -- named arrays: the place-recognition index (vocabulary, BoW), others
    name        TEXT PRIMARY KEY,
    dtype       TEXT NOT NULL,
    shape       TEXT NOT NULL,     -- JSON
    data        BLOB NOT NULL,
    crc         INTEGER NOT NULL
);
"""

#: Every released schema version's definition (RTAB-Map's habit): files are checked against it and
#: migrated from it.
SCHEMAS: dict[int, str] = {1: SCHEMA_V1, 2: SCHEMA_V2}

_I, _F, _T, _B = "INTEGER", "REAL", "TEXT", "BLOB"
#: Columns of each table in schema order: (name, type, nullable). ``crc`` columns are implied (v2).
_COLUMNS: dict[str, tuple[tuple[str, str, bool], ...]] = {
    "meta": (("key", _T, False), ("value", _T, False)),
    "node": (("id", _I, False), ("sequence", _I, False), ("frame_id", _I, False), ("source", _T, False),
             ("width", _I, False), ("height", _I, False), ("thumbnail", _B, False), ("image", _B, True),
             ("descriptor", _B, True), ("descriptor_dtype", _T, True), ("descriptor_shape", _T, True),
             ("pose_gt", _T, True)),
    "feature": (("node_id", _I, False), ("kind", _T, False), ("count", _I, False), ("keypoints", _B, False),
                ("kp_dtype", _T, False), ("descriptors", _B, False), ("desc_dtype", _T, False),
                ("desc_shape", _T, False)),
    "edge": (("a", _I, False), ("b", _I, False), ("kind", _T, False), ("inliers", _I, False),
             ("similarity", _F, False), ("flow_px", _F, False), ("relative_motion", _T, True)),
    "frame": (("id", _I, False), ("sequence", _I, False), ("seq_index", _I, False), ("source", _T, False),
              ("node_id", _I, True), ("status", _T, False)),
    "array": (("name", _T, False), ("dtype", _T, False), ("shape", _T, False), ("data", _B, False)),
}
_TABLES = tuple(_COLUMNS)


def _columns(table: str, version: int) -> tuple[tuple[str, str, bool], ...]:
    cols = _COLUMNS[table]
    if version >= 2:
        if table == "node":
            cols = cols + (("image_crc", _I, True),)
        cols = cols + (("crc", _I, False),)
    return cols


def _header_sql(version: int) -> str:
    return f"PRAGMA application_id = {APPLICATION_ID};\nPRAGMA user_version = {version};\n" + SCHEMAS[version]


@lru_cache(maxsize=None)
def _expected_master(version: int) -> frozenset[tuple[str, str, str, str | None]]:
    """``sqlite_master`` rows (type, name, tbl_name, sql) of a fresh map of schema ``version``."""
    con = sqlite3.connect(":memory:")
    try:
        con.executescript(SCHEMAS[version])
        return frozenset(con.execute("SELECT type, name, tbl_name, sql FROM sqlite_master"))
    finally:
        con.close()


# ---------------------------------------------------------------------- row checksums
def _row_crc(values: Iterable) -> int:
    """CRC-32 of a row's values in a type-tagged encoding (so ``1``, ``1.0``, ``'1'`` and ``b'1'``
    differ and no two rows concatenate alike). Floats are hashed as SQLite returns them (-0.0 as 0.0)."""
    c = 0
    for v in values:
        if v is None:
            c = zlib.crc32(b"N", c)
        elif isinstance(v, int):
            c = zlib.crc32(b"I" + v.to_bytes(8, "little", signed=True), c)
        elif isinstance(v, float):
            c = zlib.crc32(b"F" + struct.pack("<d", v + 0.0), c)
        elif isinstance(v, str):
            b = v.encode("utf-8")
            c = zlib.crc32(b, zlib.crc32(b"T" + len(b).to_bytes(8, "little"), c))
        else:
            b = bytes(v)
            c = zlib.crc32(b, zlib.crc32(b"B" + len(b).to_bytes(8, "little"), c))
    return c


def _coerce(value, kind: str, nullable: bool, what: str):
    """A value as the column stores it (so the checksum written is the one read back)."""
    if value is None:
        if not nullable:
            raise TopomapError(f"cannot store {what}: it is empty")
        return None
    if kind == _I:
        return int(value)
    if kind == _F:
        v = float(value)
        if not math.isfinite(v):  # SQLite stores NaN as NULL
            raise TopomapError(f"cannot store {what}: {v} is not a finite number")
        return v + 0.0
    if kind == _T:
        return display_name(str(value))
    return bytes(value)


def _sealed(table: str, values: tuple) -> tuple:
    """The row to insert into a schema-2 table: values coerced to their column types, checksums added."""
    cols = _COLUMNS[table]
    vals = [_coerce(v, k, n, f"{table}.{c}") for v, (c, k, n) in zip(values, cols)]
    if table == "node":
        image = vals[7]
        vals.append(None if image is None else zlib.crc32(image))
        vals.append(_row_crc(vals[:7] + vals[8:]))
    else:
        vals.append(_row_crc(vals))
    return tuple(vals)


def _insert(con: sqlite3.Connection, table: str, rows: Iterable[tuple], *, replace: bool = False) -> None:
    n = len(_columns(table, SCHEMA_VERSION))
    verb = "INSERT OR REPLACE" if replace else "INSERT"
    con.executemany(f"{verb} INTO {table} VALUES ({','.join('?' * n)})", (_sealed(table, r) for r in rows))


# ---------------------------------------------------------------------- array and image codecs
def _pack(arr: np.ndarray) -> tuple[bytes, str, str]:
    a = np.ascontiguousarray(arr)
    dt = a.dtype.newbyteorder("<") if a.dtype.byteorder not in ("|", "<") else a.dtype
    a = a.astype(dt, copy=False)
    return a.tobytes(), dt.str, json.dumps(list(a.shape))


def _unpack(data: bytes | None, dtype: str, shape: str, what: str, *, dtypes: Iterable[str] = _ARRAY_DTYPES,
            ndim: int | None = None) -> np.ndarray:
    """Raw bytes + dtype + JSON shape -> array, after checking the dtype against ``dtypes`` and the
    byte length against the shape. Raises :class:`MapFormatError` (the caller's message prefix)."""
    if dtype not in dtypes:
        raise _Bad(f"{what} has dtype {dtype!r}, expected {' or '.join(sorted(dtypes))}")
    shp = _json(shape, f"the shape of {what}", 1000)
    if not isinstance(shp, list) or len(shp) > 8 or not all(type(s) is int and 0 <= s <= 2**40 for s in shp):
        raise _Bad(f"{what} has an invalid shape {shape[:60]!r}")
    if ndim is not None and len(shp) != ndim:
        raise _Bad(f"{what} has {len(shp)} dimensions, expected {ndim}")
    dt = np.dtype(dtype)
    expected = math.prod(shp) * dt.itemsize
    if data is None or len(data) != expected:
        raise _Bad(f"{what} holds {0 if data is None else len(data)} bytes, its shape {shp} needs {expected}")
    return np.frombuffer(data, dtype=dt).reshape(shp).copy()


def encode_image(img: np.ndarray, fmt: str = "png", quality: int = 90) -> bytes:
    """A ``(H, W) uint8`` image as the bytes the map stores: ``png`` or ``jpeg`` (``quality`` 1..100)."""
    if fmt == "jpeg":
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    else:
        ok, buf = cv2.imencode(".png", img)
    if not ok:  # pragma: no cover - OpenCV encodes any uint8 array
        raise TopomapError(f"could not encode an image as {fmt.upper()}")
    return buf.tobytes()


def _node_images(n: Node, cfg: BuildConfig) -> tuple[bytes, bytes | None]:
    """The thumbnail and keyframe image bytes of a node in the map's format (the keyframe image as
    the build encoded it, if it did)."""
    thumb = encode_image(n.thumbnail, cfg.image_format, cfg.thumbnail_quality)
    image = as_bytes(getattr(n, "image_data", None))
    if image is None and n.image is not None:
        image = encode_image(n.image, cfg.image_format, cfg.image_quality)
    return thumb, image


def _decode_blob(data: bytes, what: str, *, exact: tuple[int, int] | None = None,
                 at_most: tuple[int, int] | None = None) -> np.ndarray:
    """A map image BLOB (PNG or JPEG) -> ``(h, w) uint8``, through the image gate's limits."""
    limit = exact or at_most or (MAX_WORKING_SIDE_PX, MAX_WORKING_SIDE_PX)
    try:
        img = decode_image(data, max_pixels=limit[0] * limit[1], max_size=limit, formats=("PNG", "JPEG"), what=what)
    except DatasetError as e:
        raise _Bad(str(e)) from None
    if exact is not None and (img.shape[1], img.shape[0]) != tuple(exact):
        raise _Bad(f"{what} is {img.shape[1]}x{img.shape[0]} px, the node {exact[0]}x{exact[1]}")
    return img


# ---------------------------------------------------------------------- errors and small checks
class _Bad(Exception):
    """A validation failure inside the reader; becomes one MapFormatError line naming the map."""


def _damaged(path: Path, what: str) -> MapFormatError:
    what = " ".join(str(what).split())  # one line, whatever SQLite's message held
    what = what if len(what) <= 240 else what[:237] + "..."
    return MapFormatError(f"map {display_name(path.name)} is damaged: {what}; rebuild it (topomap build) or restore a copy")


def _json(text: str, what: str, max_chars: int = _MAX_JSON_CHARS):
    if not isinstance(text, str):
        raise _Bad(f"{what} is not text")
    if len(text) > max_chars:
        raise _Bad(f"{what} is {len(text)} characters long, more than {max_chars}")
    try:
        return json.loads(text)
    except (ValueError, RecursionError):  # JSONDecodeError is a ValueError; deep nesting recurses
        raise _Bad(f"{what} is not valid JSON") from None


def _finite_numbers(v, n: tuple[int, int]) -> bool:
    return (isinstance(v, list) and n[0] <= len(v) <= n[1]
            and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v))


# ---------------------------------------------------------------------- files, locks, recovery
def check_writable(path: str | Path, *, overwrite: bool = False, append: bool = False) -> Path:
    """Validate a map output path before any work is done (clear one-line errors).

    ``append``: the map must exist and be writable in place (``--append``, ``index``, ``upgrade``).
    """
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
            raise DatasetError(f"map {path} does not exist; build it first (without --append)")
        if not path.is_file():
            raise DatasetError(f"{path} is not a regular file")
        if not os.access(path, os.W_OK) or not os.access(parent, os.W_OK):
            raise DatasetError(f"map {path} is read-only (it or its folder is not writable); copy it somewhere writable first")
        return path
    if path.exists() and not overwrite:
        raise DatasetError(f"{path} already exists; use --force to overwrite it or --append to add this sequence to it")
    if path.exists() and not path.is_file():
        raise DatasetError(f"{path} is not a regular file")
    if not os.access(parent, os.W_OK):
        raise DatasetError(f"folder {parent} is not writable")
    return path


def _companion(path: Path, suffix: str) -> Path:
    return path.with_name(path.name + suffix)


def _temp_path(path: Path) -> Path:
    return path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(3)}.tmp")


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True
    return True


def _clean_stale_temp(path: Path) -> None:
    """Remove the temporary files (and their journals) that dead topomap processes left beside the
    map (``.MAP.PID[.TOKEN].tmp``). Best effort: a file of a live process, a recent one, or one we
    may not delete stays."""
    folder = path.parent if str(path.parent) else Path(".")
    pattern = re.compile(rf"\.{re.escape(path.name)}\.(\d+)(?:\.[0-9a-f]+)?\.tmp(?:-journal|-wal|-shm)?")
    try:
        entries = list(folder.iterdir())
    except OSError:
        return
    now = time.time()
    for p in entries:
        m = pattern.fullmatch(p.name)
        if m is None:
            continue
        try:
            if _pid_alive(int(m.group(1))) or now - p.lstat().st_mtime < STALE_TEMP_AGE_S:
                continue
            p.unlink()
            log.info("removed %s, left by a topomap process that no longer runs", p.name)
        except OSError:
            continue


# POSIX record locks belong to a process and a file: closing *any* descriptor of the map file drops
# every lock this process holds on it, SQLite's included (SQLite guards only its own descriptors).
# So Python reads a map's header only while no SQLite connection of this process has that file open;
# the connections are counted here, per file identity.
_OPEN: dict[tuple[int, int], list] = {}  # (st_dev, st_ino) -> [open connections, header bytes]
_OPEN_GUARD = threading.Lock()


def _file_key(path: Path) -> tuple[int, int]:
    st = os.stat(path)
    return st.st_dev, st.st_ino


def _read_header(path: Path) -> bytes:
    """The first 100 bytes of the file (as seen when this process first opened it, while it does)."""
    with _OPEN_GUARD:
        entry = _OPEN.get(_file_key(path))
        if entry is not None:
            return entry[1]
        with open(path, "rb") as fh:
            return fh.read(100)


def _open_here(path: Path) -> bool:
    with _OPEN_GUARD:
        try:
            return _file_key(path) in _OPEN
        except OSError:
            return False


@contextlib.contextmanager
def _opened(path: Path, header: bytes, *, readonly: bool, immutable: bool = False,
            timeout_s: float = BUSY_TIMEOUT_S, register: bool = True) -> Iterator[sqlite3.Connection]:
    """A configured connection to the map at ``path``, counted in ``_OPEN`` while it is open."""
    key = _file_key(path) if register else None
    if key is not None:
        with _OPEN_GUARD:
            entry = _OPEN.setdefault(key, [0, header])
            entry[0] += 1
    try:
        con = _connect(path, readonly=readonly, immutable=immutable, timeout_s=timeout_s)
        try:
            yield con
        finally:
            with contextlib.suppress(sqlite3.Error):
                if con.in_transaction:
                    con.execute("ROLLBACK")
            con.close()
    finally:
        if key is not None:
            with _OPEN_GUARD:
                entry[0] -= 1
                if entry[0] == 0:
                    _OPEN.pop(key, None)


def _check_map_file(path: Path) -> bytes:
    """Identity checks before SQLite opens the file: regular file, SQLite header, topomap's id.
    Returns the header (100 bytes)."""
    shown = display_name(str(path))
    if not path.exists():
        if path.is_symlink():
            raise MapFormatError(f"map {shown} is a broken symbolic link")
        raise MapFormatError(f"map {shown} does not exist; build one with `topomap build SOURCE -o {display_name(path.name)}`")
    if path.is_dir():
        raise MapFormatError(f"{shown} is a folder, not a map file")
    try:
        st = path.stat()
        if not stat.S_ISREG(st.st_mode):
            raise MapFormatError(f"{shown} is not a regular file (a FIFO or a device?), not a map file")
        head = _read_header(path)
    except OSError as e:
        raise MapFormatError(f"cannot read map {shown}: {e.strerror or e}") from None
    if len(head) == 0:
        raise MapFormatError(f"{shown} is an empty file, not a topomap map")
    if not head.startswith(_SQLITE_MAGIC):
        raise MapFormatError(f"{shown} is not a topomap map file (build one with `topomap build`)")
    if len(head) < 100:
        raise MapFormatError(f"map {shown} is truncated; rebuild it or restore a copy")
    app_id = int.from_bytes(head[68:72], "big", signed=True)
    if app_id != APPLICATION_ID:
        raise MapFormatError(f"{shown} is an SQLite database but not a topomap map")
    return head


def _check_size(con: sqlite3.Connection, path: Path, shown: Path) -> None:
    """A whole number of pages, at least as many as the header says (asked inside the read
    transaction, so no commit is half-written meanwhile)."""
    page = con.execute("PRAGMA page_size").fetchone()[0]
    pages = con.execute("PRAGMA page_count").fetchone()[0]
    size = os.stat(path).st_size
    if page < 512 or size % page:
        raise _damaged(shown, "the file is truncated (not a whole number of pages)")
    if size < pages * page:
        raise _damaged(shown, f"the file is truncated ({size} bytes of {pages * page})")


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0


def _is_wal(header: bytes) -> bool:
    return len(header) >= 20 and header[18] == 2


def _configure(con: sqlite3.Connection, *, readonly: bool) -> None:
    # A stranger's schema must not run functions in views or triggers (SQLite >= 3.31; ignored before).
    con.execute("PRAGMA trusted_schema = OFF")
    con.execute("PRAGMA cell_size_check = ON")
    if readonly:
        con.execute("PRAGMA query_only = ON")


def _connect(path: Path, *, readonly: bool, immutable: bool = False, timeout_s: float = BUSY_TIMEOUT_S) -> sqlite3.Connection:
    if readonly:
        uri = f"file:{path.resolve().as_posix()}?mode=ro" + ("&immutable=1" if immutable else "")
        con = sqlite3.connect(uri, uri=True, timeout=timeout_s, isolation_level=None)
    else:
        con = sqlite3.connect(path, timeout=timeout_s, isolation_level=None)
    try:
        _configure(con, readonly=readonly)
    except _SQLITE_ERRORS:
        con.close()
        raise
    return con


def _roll_back_hot_journal(path: Path, header: bytes) -> bool:
    """Let SQLite roll back a hot journal (a writer killed mid-commit) in place; True if it could.

    Any read-write connection does it on its first read, under SQLite's own locks: a journal that
    belongs to a live writer is not hot and is left alone. The file returns to its last commit."""
    if not (os.access(path, os.W_OK) and os.access(path.parent if str(path.parent) else Path("."), os.W_OK)):
        return False
    journal = _companion(path, "-journal")
    try:
        with _opened(path, header, readonly=False, timeout_s=5.0) as con:
            con.execute("SELECT count(*) FROM sqlite_master").fetchone()
            if journal.exists():
                # Not hot: a live writer's (it holds the write lock), or a stale one whose header
                # never reached the disk. Under the write lock no writer exists: remove it then.
                con.execute("PRAGMA busy_timeout = 0")
                try:
                    con.execute("BEGIN IMMEDIATE")
                except sqlite3.OperationalError:
                    return True  # a live writer: its journal is its own business
                journal.unlink(missing_ok=True)
                con.execute("ROLLBACK")
                return True
    except _SQLITE_ERRORS:
        return False
    log.info("map %s: rolled back the unfinished write of an interrupted topomap process; the map "
             "is as it was at its last complete write", display_name(path.name))
    return True


def _copy_for_reading(path: Path, stack: contextlib.ExitStack) -> Path:
    """A private copy of the map and its journal/WAL in a temporary folder, recovered there: how a
    read-only map with a hot journal or unmerged WAL is read without writing beside it."""
    tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="topomap-read-")))
    copy = tmp / "map.topomap"
    shutil.copyfile(path, copy)
    for suffix in ("-journal", "-wal"):
        src = _companion(path, suffix)
        if src.exists() and src.stat().st_size:
            shutil.copyfile(src, _companion(copy, suffix))
    con = _connect(copy, readonly=False)
    try:
        con.execute("SELECT count(*) FROM sqlite_master").fetchone()
        if con.execute("PRAGMA journal_mode").fetchone()[0] == "wal":
            con.execute("PRAGMA journal_mode = DELETE")
    finally:
        con.close()
    return copy


def _check_version(con: sqlite3.Connection, path: Path) -> int:
    version = con.execute("PRAGMA user_version").fetchone()[0]
    if version > SCHEMA_VERSION:
        raise MapFormatError(
            f"map {display_name(path.name)} was written by a newer topomap (map schema {version}, this topomap "
            f"{__version__} reads up to {SCHEMA_VERSION}); upgrade topomap: pip install -U appearance-topomap"
        )
    if version < 1:
        raise MapFormatError(f"map {display_name(path.name)} has no schema version; it is not a topomap map")
    if version not in SCHEMAS:
        raise MapFormatError(f"map {display_name(path.name)} has unknown schema version {version}; it is not a map topomap wrote")
    return version


def _check_schema(con: sqlite3.Connection, version: int, path: Path) -> None:
    """``sqlite_master`` must be exactly what topomap writes for this version: a stranger's view,
    trigger or virtual table would run (or recurse forever) inside our queries."""
    actual = frozenset(con.execute("SELECT type, name, tbl_name, sql FROM sqlite_master"))
    expected = _expected_master(version)
    if actual == expected:
        return
    names = {(t, n): s for t, n, _, s in expected}
    rank = {"view": 0, "trigger": 1, "table": 2, "index": 3}  # name the most telling difference
    for t, n, _, s in sorted(actual - expected, key=lambda r: (rank.get(r[0], 4), r[1])):
        if (t, n) in names:
            what = f"its {t} {n!r} is not defined as topomap defines it"
        else:
            what = f"it holds a {t} {n!r} that topomap never writes"
        break
    else:
        t, n = sorted((t, n) for t, n, _, _ in expected - actual)[0]
        what = f"its {t} {n!r} is missing"
    raise MapFormatError(
        f"map {display_name(path.name)} is not a map as topomap writes it ({what}); topomap reads only the "
        "maps it wrote: rebuild this one from its images with `topomap build`"
    )


@contextlib.contextmanager
def _reading(path: Path) -> Iterator[tuple[sqlite3.Connection, int, Path]]:
    """A validated read-only connection inside one read transaction: ``(con, version, file read)``.

    A hot journal (a writer killed mid-commit) is rolled back first, in place when the map is
    writable, else in a private temporary copy; a WAL-mode map is opened immutable (or copied when
    its WAL holds commits), so reading leaves no ``-wal``/``-shm`` files behind."""
    path = Path(path)
    header = _check_map_file(path)
    _clean_stale_temp(path)
    with contextlib.ExitStack() as stack:
        target = path
        journal, wal = _companion(path, "-journal"), _companion(path, "-wal")
        try:
            if not _open_here(path):  # else this process reads it already: no journal can be hot
                # a journal: hot, a live writer's, or a stale (even empty) leftover
                if journal.exists() and not _roll_back_hot_journal(path, header) and _size(journal) > 0:
                    target = _copy_for_reading(path, stack)  # read-only: recover in a private copy
                elif _is_wal(header) and _size(wal) > 0:
                    target = _copy_for_reading(path, stack)
                header = _read_header(target) if target is not path else _read_header(path)
            con = stack.enter_context(_opened(target, header, readonly=True, immutable=_is_wal(header),
                                              register=target is path))
        except OSError as e:
            raise MapFormatError(f"cannot read map {display_name(str(path))}: {e.strerror or e}") from None
        except _SQLITE_ERRORS as e:
            raise _damaged(path, f"SQLite cannot open it ({e})") from None
        try:
            con.execute("BEGIN")  # one snapshot: a writer committing meanwhile waits for us
            version = _check_version(con, path)  # the first read: takes the shared lock
            _check_size(con, target, path)
            _check_schema(con, version, path)
        except sqlite3.OperationalError as e:
            if "readonly" in str(e):  # a journal turned hot after our check (its writer just died)
                raise MapFormatError(f"map {display_name(path.name)} was being written by a process that just "
                                     "stopped; run the command again (the unfinished write is rolled back)") from None
            raise _damaged(path, f"SQLite cannot read it ({e})") from None
        except _SQLITE_ERRORS as e:
            raise _damaged(path, f"SQLite cannot read it ({e})") from None
        yield con, version, target


@contextlib.contextmanager
def _locked(path: Path, timeout_s: float, header: bytes) -> Iterator[sqlite3.Connection]:
    """A read-write connection holding the map's write lock (``BEGIN IMMEDIATE``), on the file that
    is at ``path`` now (a writer that waited while another replaced the file reconnects)."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            before = _file_key(path)
        except OSError as e:
            raise MapFormatError(f"cannot open map {display_name(str(path))}: {e.strerror or e}") from None
        with _opened(path, header, readonly=False, timeout_s=max(0.0, deadline - time.monotonic())) as con:
            try:
                con.execute("BEGIN IMMEDIATE")  # also rolls back a hot journal first
            except sqlite3.OperationalError as e:
                if "locked" in str(e) or "busy" in str(e):
                    raise MapConflictError(
                        f"map {display_name(path.name)} is being written by another topomap command (build --append, "
                        f"index or upgrade) for more than {timeout_s:.0f} s; run this one again when it has finished"
                    ) from None
                raise _damaged(path, f"SQLite cannot lock it ({e})") from None
            except _SQLITE_ERRORS as e:
                raise _damaged(path, f"SQLite cannot open it ({e})") from None
            try:
                same = _file_key(path) == before
            except OSError:
                same = False
            if same:
                con.execute(f"PRAGMA busy_timeout = {int(BUSY_TIMEOUT_S * 1000)}")
                yield con
                return
        if time.monotonic() > deadline:
            raise MapConflictError(f"map {display_name(path.name)} keeps being replaced by another topomap command; "
                                   "run this one again when it has finished")
        header = _read_header(path)


@contextlib.contextmanager
def _replacing(path: Path) -> Iterator[None]:
    """Guard for ``os.replace(new, path)``: hold the old map's write lock meanwhile (a writer of the
    old file must not commit into a file that is being replaced), and remove a journal or WAL that
    belongs to no file (it would be rolled into the new one)."""
    with contextlib.ExitStack() as stack:
        locked = False
        if path.exists():
            try:
                header = _read_header(path)
                if header.startswith(_SQLITE_MAGIC):
                    stack.enter_context(_locked(path, LOCK_TIMEOUT_S, header))
                    locked = True
            except (OSError, MapFormatError) as e:
                if isinstance(e, MapConflictError):
                    raise
        if not locked:  # no map there (or a damaged one): its journal and WAL belong to nothing
            for suffix in ("-journal", "-wal", "-shm"):
                _companion(path, suffix).unlink(missing_ok=True)
        yield


# ---------------------------------------------------------------------- writing
def _meta_rows(m: TopoMap, revision: int) -> dict[str, object]:
    rows = {
        k: v for k, v in m.meta.items() if k not in _RESERVED_META and not k.startswith("_")
    }  # other modules' keys (a calibration, experiences, ...): kept as they are
    rows.update({
        "format": FORMAT_NAME,
        "schema_version": SCHEMA_VERSION,
        "topomap_version": __version__,
        "created_utc": m.meta.get("created_utc") or time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "modified_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "build_config": to_dict(m.config),
        "camera": m.camera.to_dict(),
        "feature_kind": m.feature_kind,
        "sequences": m.sequences,
        "descriptor": m.meta.get("descriptor"),
        "revision": revision,
    })
    return rows


def _clean_json(v):
    """JSON-able value with every string storable as UTF-8 (file names from any file system)."""
    if isinstance(v, str):
        return display_name(v)
    if isinstance(v, dict):
        return {display_name(str(k)): _clean_json(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_clean_json(x) for x in v]
    return v


def _node_rows(nodes: Iterable[Node], cfg: BuildConfig) -> Iterator[tuple]:
    for n in nodes:
        if n.descriptor is not None:
            d_blob, d_dt, d_shape = _pack(n.descriptor)
        else:
            d_blob = d_dt = d_shape = None
        yield (n.id, n.sequence, n.frame_id, n.source, n.features.image_size[0], n.features.image_size[1],
               *_node_images(n, cfg),
               d_blob, d_dt, d_shape, json.dumps([float(v) for v in n.pose_gt]) if n.pose_gt is not None else None)


def _feature_rows(nodes: Iterable[Node]) -> Iterator[tuple]:
    for n in nodes:
        kp, kp_dt, _ = _pack(n.features.keypoints.astype(np.float32))
        de, de_dt, de_shape = _pack(n.features.descriptors)
        yield (n.id, n.features.kind, len(n.features), kp, kp_dt, de, de_dt, de_shape)


def _edge_rows(edges: Iterable[Edge]) -> Iterator[tuple]:
    for e in edges:
        motion = e.relative_motion  # the keyframe pair's geometry (topomap.relative_motion)
        yield (e.a, e.b, e.kind.value, e.inliers, e.similarity, e.flow_px,
               None if motion is None else json.dumps(motion, separators=(",", ":")))


def _frame_rows(frames: Iterable[FrameRecord]) -> Iterator[tuple]:
    for f in frames:
        yield (f.id, f.sequence, f.index, f.source, f.node, f.status)


def _write_meta_and_arrays(con: sqlite3.Connection, m: TopoMap, revision: int) -> None:
    rows = _meta_rows(m, revision)
    _insert(con, "meta", ((k, json.dumps(_clean_json(v))) for k, v in rows.items()), replace=True)
    con.execute("DELETE FROM array")
    arrays = dict(m.index.to_arrays()) if m.index is not None else {}
    for name, arr in getattr(m, "arrays", {}).items():
        if _INDEX_ARRAY.fullmatch(name):
            raise TopomapError(f"array name {name!r} is reserved for the place-recognition index")
        arrays[name] = arr
    packed = [(name, *_reorder(_pack(np.asarray(arr)))) for name, arr in arrays.items()]
    for name, dtype, _, _ in packed:
        if dtype not in _ARRAY_DTYPES:
            raise TopomapError(f"cannot store array {name!r} of dtype {dtype}: only numbers and booleans (no pickle)")
    _insert(con, "array", packed)
    counts = {t: con.execute(f"SELECT count(*) FROM {t}").fetchone()[0] for t in _TABLES if t != "meta"}
    _insert(con, "meta", [("row_counts", json.dumps(counts))], replace=True)


def _reorder(packed: tuple[bytes, str, str]) -> tuple[str, str, bytes]:
    blob, dt, shape = packed
    return dt, shape, blob


def _write_new(m: TopoMap, target: Path) -> None:
    """Write ``m`` as a fresh schema-``SCHEMA_VERSION`` file at ``target`` (which must not exist)."""
    with contextlib.closing(sqlite3.connect(target, isolation_level=None)) as con:
        con.executescript(_header_sql(SCHEMA_VERSION))
        con.execute("BEGIN")
        try:
            nodes = sorted(m.nodes.values(), key=lambda n: n.id)
            _insert(con, "node", _node_rows(nodes, m.config))
            _insert(con, "feature", _feature_rows(nodes))
            _insert(con, "edge", _edge_rows(sorted(m.edges.values(), key=lambda e: e.key)))
            _insert(con, "frame", _frame_rows(m.frames))
            revision = int(m.meta.get("revision") or 0) + 1
            _write_meta_and_arrays(con, m, revision)
            con.execute("COMMIT")
        except BaseException:
            if con.in_transaction:
                con.execute("ROLLBACK")
            raise
    m.meta["revision"] = revision  # the map in memory is now the file's


def _discard(tmp: Path) -> None:
    for leftover in (tmp, _companion(tmp, "-journal")):
        with contextlib.suppress(OSError):
            leftover.unlink(missing_ok=True)


def save_map(m: TopoMap, path: str | Path, *, overwrite: bool = False) -> Path:
    """Write ``m`` as a new map file; atomic: the target appears (or is replaced) only when complete.

    Replacing an existing map waits for (or is refused by) a command that is writing it."""
    path = check_writable(path, overwrite=overwrite)
    _clean_stale_temp(path)
    tmp = _temp_path(path)
    try:
        _write_new(m, tmp)
        with _replacing(path):
            with contextlib.suppress(OSError):
                os.chmod(tmp, stat.S_IMODE(path.stat().st_mode))
            os.replace(tmp, path)
    except BaseException:
        _discard(tmp)
        raise
    return path


@dataclass
class MapUpdate:
    """One locked read-modify-write of a map file, from :func:`open_for_update`.

    ``map`` was read under the write lock, which is held until :meth:`commit` (or the end of the
    ``with`` block, which rolls back): nothing can change the file in between."""

    path: Path
    map: TopoMap
    _con: sqlite3.Connection = field(repr=False)
    _node_ids: frozenset = field(repr=False)
    _frames: int = field(repr=False)
    _revision: int = field(repr=False)
    committed: bool = False

    def commit(self, m: TopoMap | None = None) -> Path:
        """Write the growth of the map (``self.map`` or the map given): its new nodes (ids not in
        the file) and new frames, every edge (upserted), the header, the index and named arrays."""
        m = self.map if m is None else m
        if self.committed:
            raise TopomapError("this map update was already committed")
        con = self._con
        if [f.id for f in m.frames[: self._frames]] != list(range(self._frames)):
            raise TopomapError("the map's existing frames were changed; updates only add frames")
        new_nodes = [n for i, n in sorted(m.nodes.items()) if i not in self._node_ids]
        try:
            _insert(con, "node", _node_rows(new_nodes, m.config))
            _insert(con, "feature", _feature_rows(new_nodes))
            _insert(con, "frame", _frame_rows(m.frames[self._frames :]))
            _insert(con, "edge", _edge_rows(sorted(m.edges.values(), key=lambda e: e.key)), replace=True)
            _write_meta_and_arrays(con, m, self._revision + 1)
            con.execute("COMMIT")
        except sqlite3.IntegrityError as e:  # pragma: no cover - prevented by the lock and the id checks
            con.execute("ROLLBACK")
            raise MapConflictError(f"map {display_name(self.path.name)} could not take the update ({e}); run the command again") from None
        except BaseException:
            if con.in_transaction:
                con.execute("ROLLBACK")
            raise
        self.committed = True
        m.meta["revision"] = self._revision + 1
        return self.path


@contextlib.contextmanager
def open_for_update(path: str | Path, *, images: bool = False, timeout_s: float = LOCK_TIMEOUT_S) -> Iterator[MapUpdate]:
    """Lock a map for one read-modify-write: ``with open_for_update(p) as u: grow(u.map); u.commit()``.

    The write lock is taken first (waiting up to ``timeout_s`` for another writer, then
    :class:`MapConflictError`), the map is read and validated under it, and it is held until the
    commit; leaving the block without committing rolls back. A map of an older schema is upgraded
    first (:func:`upgrade_map`). Readers are not blocked until the commit itself."""
    path = check_writable(path, append=True)
    header = _check_map_file(path)
    _clean_stale_temp(path)
    with _locked(path, timeout_s, header) as con:
        old = _check_version(con, path) < SCHEMA_VERSION
    if old:
        upgrade_map(path)
        header = _check_map_file(path)
    with _locked(path, timeout_s, header) as con:
        try:
            version = _check_version(con, path)
            _check_size(con, path, path)
            _check_schema(con, version, path)
            m = _read(con, path, version, images)
        except _SQLITE_ERRORS as e:
            raise _damaged(path, f"SQLite cannot read it ({e})") from None
        yield MapUpdate(path, m, con, frozenset(m.nodes), len(m.frames), int(m.meta.get("revision") or 0))


def update_map(m: TopoMap, path: str | Path, *, first_new_node: int, first_new_frame: int) -> Path:
    """Write the growth of a map loaded earlier back in place, in one transaction.

    Inserts the nodes and frames from the given ids on, upserts every edge and rewrites the header,
    the index and the named arrays. Refused with :class:`MapConflictError` when the file changed
    since ``m`` was loaded (its ``revision``), so a concurrent writer's update is never overwritten;
    an interruption rolls the whole update back. Prefer :func:`open_for_update`, which cannot
    conflict."""
    path = Path(path)
    with open_for_update(path) as u:
        current = u.map
        loaded = int(m.meta.get("revision") or 0)
        if loaded != u._revision or current.next_node_id() > first_new_node or len(current.frames) != first_new_frame:
            raise MapConflictError(
                f"map {display_name(path.name)} changed since it was loaded (another topomap command wrote to it); "
                "load it again and redo this change"
            )
        u._node_ids = frozenset(i for i in m.nodes if i < first_new_node)
        u._frames = first_new_frame
        return u.commit(m)


# ---------------------------------------------------------------------- migration
def _v1_to_v2(src: sqlite3.Connection) -> Iterator[tuple[str, Iterable[tuple]]]:
    """Schema 1 rows as schema 2 rows (without checksums, which ``_insert`` adds)."""
    meta = {k: v for k, v in src.execute("SELECT key, value FROM meta")}
    meta["schema_version"] = json.dumps(2)
    meta.setdefault("revision", json.dumps(0))
    meta["modified_utc"] = json.dumps(time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()))
    yield "meta", sorted(meta.items())
    for table in ("node", "feature", "edge", "frame", "array"):
        cols = ", ".join(c for c, _, _ in _COLUMNS[table])
        yield table, src.execute(f"SELECT {cols} FROM {table} ORDER BY rowid")


#: Row transforms from each older schema to the current one.
_MIGRATIONS = {1: _v1_to_v2}


def upgrade_map(path: str | Path) -> tuple[int, int]:
    """Rewrite a map of an older schema as the current schema (``topomap upgrade MAP``).

    The old map is validated completely first (an upgrade never seals damage with fresh checksums),
    then written to a temporary file that replaces it atomically while the map's write lock is
    held. Returns ``(old version, new version)``; a current map is left untouched."""
    path = check_writable(Path(path), append=True)
    header = _check_map_file(path)
    _clean_stale_temp(path)
    with _locked(path, LOCK_TIMEOUT_S, header) as con:
        version = _check_version(con, path)
        if version == SCHEMA_VERSION:
            return version, version
        try:
            _check_size(con, path, path)
            _check_schema(con, version, path)
            _read(con, path, version, images=True)
        except _SQLITE_ERRORS as e:
            raise _damaged(path, f"SQLite cannot read it ({e})") from None
        tmp = _temp_path(path)
        try:
            with contextlib.closing(sqlite3.connect(tmp, isolation_level=None)) as dst:
                dst.executescript(_header_sql(SCHEMA_VERSION))
                dst.execute("BEGIN")
                for table, rows in _MIGRATIONS[version](con):
                    _insert(dst, table, rows)
                counts = {t: dst.execute(f"SELECT count(*) FROM {t}").fetchone()[0] for t in _TABLES if t != "meta"}
                _insert(dst, "meta", [("row_counts", json.dumps(counts))], replace=True)
                dst.execute("COMMIT")
            with contextlib.suppress(OSError):
                os.chmod(tmp, stat.S_IMODE(path.stat().st_mode))
            os.replace(tmp, path)  # under the old file's write lock: no writer commits into it meanwhile
        except BaseException:
            _discard(tmp)
            raise
    log.info("upgraded map %s from schema %d to %d", display_name(path.name), version, SCHEMA_VERSION)
    return version, SCHEMA_VERSION


def map_schema_version(path: str | Path) -> int:
    """The schema version of a map file (after the same identity checks as reading)."""
    with _reading(Path(path)) as (_, version, _):
        return version


# ---------------------------------------------------------------------- reading
def load_map(path: str | Path, *, images: bool = False) -> TopoMap:
    """Open a map file. ``images=True`` also decodes the stored keyframe images (slower).

    Raises :class:`MapFormatError` with one clear line for a missing, foreign, truncated, damaged
    or newer-version file. The file is opened read-only and never modified (an older schema is
    migrated in memory); the only write is SQLite rolling back a killed writer's hot journal.
    """
    path = Path(path)
    with _reading(path) as (con, version, _):
        try:
            return _read(con, path, version, images)
        except _SQLITE_ERRORS as e:
            raise _damaged(path, f"SQLite cannot read it ({e})") from None


def _rows(con: sqlite3.Connection, table: str, version: int, *, skip: tuple[str, ...] = (), order: str = "rowid",
          where: str = "", args: tuple = ()) -> Iterator[tuple]:
    """Rows of ``table`` with every column type-checked and (schema 2) the checksum verified; the
    columns in ``skip`` are left out of the query (and of the result)."""
    cols = _columns(table, version)
    names = [c for c, _, _ in cols if c not in skip]
    pytype = {_I: int, _F: float, _T: str, _B: bytes}
    for row in con.execute(f"SELECT {', '.join(names)} FROM {table} {where} ORDER BY {order}", args):
        values = dict(zip(names, row))
        for c, kind, nullable in cols:
            if c in skip:
                continue
            v = values[c]
            if v is None:
                if not nullable:
                    raise _Bad(f"{table}.{c} is empty in row {row[0]!r}"[:200])
            elif kind == _F and type(v) is int:
                values[c] = float(v)
            elif type(v) is not pytype[kind]:
                raise _Bad(f"{table}.{c} of row {str(row[0])[:40]!r} holds {type(v).__name__} data, expected {kind}")
            elif kind == _T and len(v) > (_MAX_JSON_CHARS if c in ("value",) else _MAX_TEXT_CHARS):
                raise _Bad(f"{table}.{c} of row {str(row[0])[:40]!r} is too long")
        if version >= 2:
            covered = [values[c] for c, _, _ in cols if c not in ("crc", "image")]
            if _row_crc(covered) != values["crc"]:
                raise _Bad(f"row {str(row[0])[:40]} of table {table} fails its checksum: the file changed after topomap wrote it")
        yield tuple(values[c] for c in names if c != "crc")


def _read(con: sqlite3.Connection, path: Path, version: int, images: bool) -> TopoMap:
    try:
        return _read_checked(con, path, version, images)
    except _Bad as e:
        raise _damaged(path, str(e)) from None


def _read_meta(con, path: Path, version: int) -> dict:
    meta = {}
    for key, value in _rows(con, "meta", version):
        meta[key] = _json(value, f"header entry {key[:40]!r}")
    if meta.get("format") != FORMAT_NAME:
        raise MapFormatError(f"{display_name(path.name)} is not a topomap map (format {str(meta.get('format'))[:40]!r})")
    for key in ("build_config", "camera"):
        if key not in meta:
            raise _Bad(f"its header lacks {key!r}")
    if meta.get("schema_version", version) != version:
        raise _Bad(f"its header says schema {str(meta.get('schema_version'))[:20]}, the file {version}")
    return meta


def _check_meta(meta: dict, version: int) -> tuple[BuildConfig, CameraIntrinsics, list, dict | None]:
    try:
        config = from_dict(BuildConfig, meta["build_config"])
    except (ConfigError, DatasetError, TypeError, ValueError, KeyError, AttributeError) as e:
        raise _Bad(f"its build configuration is unreadable ({str(e)[:120]})") from None
    cam = meta["camera"]
    if not isinstance(cam, dict):
        raise _Bad("its camera is not a mapping")
    try:
        camera = CameraIntrinsics.from_dict(cam)
    except (DatasetError, ConfigError, TypeError, ValueError, AttributeError) as e:
        raise _Bad(f"its camera is unreadable ({str(e)[:120]})") from None
    if not (0 <= camera.width <= MAX_WORKING_SIDE_PX and 0 <= camera.height <= MAX_WORKING_SIDE_PX):
        raise _Bad(f"its camera size {camera.width}x{camera.height} is out of range")
    if not all(math.isfinite(d) for d in camera.distortion) or len(camera.distortion) > 14:
        raise _Bad("its camera distortion is not a list of at most 14 finite numbers")
    kind = meta.get("feature_kind", config.features.kind)
    if kind != config.features.kind:
        raise _Bad(f"its header names {str(kind)[:20]} features but was built with {config.features.kind}")
    sequences = meta.get("sequences") or []
    if not isinstance(sequences, list) or not all(isinstance(s, dict) for s in sequences):
        raise _Bad("its list of build runs (sequences) is not a list of records")
    for s in sequences:
        if not isinstance(s.get("source", ""), str):
            raise _Bad("a build run's source is not text")
    desc = meta.get("descriptor")
    if desc is not None:
        size = desc.get("size") if isinstance(desc, dict) else None
        if (not isinstance(desc, dict) or not isinstance(desc.get("kind", ""), str) or not isinstance(size, list)
                or len(size) != 2 or not all(type(v) is int and 1 <= v <= 4096 for v in size)
                or type(desc.get("patch", 8)) is not int or not 1 <= desc.get("patch", 8) <= 4096):
            raise _Bad("its whole-image descriptor entry is malformed")
    if version >= 2:
        rev = meta.get("revision")
        if type(rev) is not int or rev < 0:
            raise _Bad("its revision is not a non-negative integer")
    return config, camera, sequences, desc


def _read_checked(con: sqlite3.Connection, path: Path, version: int, images: bool) -> TopoMap:
    meta = _read_meta(con, path, version)
    config, camera, sequences, desc = _check_meta(meta, version)
    if version >= 2:
        counts = meta.get("row_counts")
        if not isinstance(counts, dict):
            raise _Bad("its header lacks the row counts")
        for t in _TABLES:
            if t == "meta":
                continue
            n = con.execute(f"SELECT count(*) FROM {t}").fetchone()[0]
            if counts.get(t) != n:
                raise _Bad(f"its {t} table holds {n} rows, the header says {str(counts.get(t))[:20]}")
    kind = config.features.kind
    try:
        det = detector(kind)
    except ConfigError as e:
        raise _Bad(str(e)) from None
    desc_dtype = "|u1" if det.binary else "<f4"
    desc_len = None if desc is None else desc["size"][0] * desc["size"][1]

    m = TopoMap(camera=camera, config=config, sequences=sequences)
    m.meta = {k: v for k, v in meta.items() if k not in _RESERVED_META}
    m.meta.update({"created_utc": meta.get("created_utc"), "topomap_version": meta.get("topomap_version"),
                   "schema_version": version, "descriptor": desc, "revision": meta.get("revision", 0)})

    feats: dict[int, Features] = {}
    node_sizes: dict[int, tuple[int, int]] = {}
    node_rows = list(_rows(con, "node", version, skip=("image",), order="id"))
    for row in node_rows:
        nid, w, h = row[0], row[4], row[5]
        if not 0 <= nid <= _MAX_ID:
            raise _Bad(f"node id {nid} is out of range")
        if not (1 <= w <= MAX_WORKING_SIDE_PX and 1 <= h <= MAX_WORKING_SIDE_PX):
            raise _Bad(f"node {nid} has a working size of {w}x{h} px")
        node_sizes[nid] = (w, h)
    for node_id, fkind, count, kp, kp_dt, de, de_dt, de_shape in _rows(con, "feature", version, order="node_id"):
        if node_id not in node_sizes:
            raise _Bad(f"features of node {node_id}, which does not exist")
        if fkind != kind:
            raise _Bad(f"node {node_id} has {fkind[:20]} features, the map {kind}")
        if not 0 <= count <= _MAX_FEATURES:
            raise _Bad(f"node {node_id} has {count} features")
        keypoints = _unpack(kp, kp_dt, json.dumps([count, 2]), f"keypoints of node {node_id}", dtypes={"<f4"})
        descriptors = _unpack(de, de_dt, de_shape, f"descriptors of node {node_id}", dtypes={desc_dtype}, ndim=2)
        if descriptors.shape != (count, det.descriptor_size):
            raise _Bad(f"descriptors of node {node_id} have shape {descriptors.shape}, expected ({count}, {det.descriptor_size})")
        w, h = node_sizes[node_id]
        if count and (not np.isfinite(keypoints).all() or np.abs(keypoints).max() > 4 * max(w, h)):
            raise _Bad(f"keypoints of node {node_id} are not finite or lie far outside its {w}x{h} image")
        if not det.binary and count and not np.isfinite(descriptors).all():
            raise _Bad(f"descriptors of node {node_id} are not finite")
        feats[node_id] = Features(keypoints, descriptors, kind, (w, h))
    for row in node_rows:
        nid, seq, frame_id, source, w, h, thumb, d_blob, d_dt, d_shape, pose = row[:11]
        if nid not in feats:
            raise _Bad(f"node {nid} has no features")
        if not (0 <= seq <= _MAX_ID and 0 <= frame_id <= _MAX_ID) or (sequences and seq >= len(sequences)):
            raise _Bad(f"node {nid} names build run {seq} / frame {frame_id}, which the map does not have")
        descriptor = None
        if d_blob is not None:
            descriptor = _unpack(d_blob, d_dt, d_shape, f"the whole-image descriptor of node {nid}", dtypes={"<f4"}, ndim=1)
            if desc_len is not None and descriptor.size != desc_len:
                raise _Bad(f"the whole-image descriptor of node {nid} has {descriptor.size} values, the map {desc_len}")
            if not np.isfinite(descriptor).all():
                raise _Bad(f"the whole-image descriptor of node {nid} is not finite")
        pose_gt = None
        if pose is not None:
            p = _json(pose, f"the ground-truth pose of node {nid}", 10_000)
            if not _finite_numbers(p, (2, 7)):
                raise _Bad(f"the ground-truth pose of node {nid} is not a list of 2 to 7 finite numbers")
            pose_gt = tuple(float(v) for v in p)
        m.nodes[nid] = Node(
            id=nid, sequence=seq, frame_id=frame_id, source=source, features=feats[nid],
            thumbnail=_decode_blob(thumb, f"the thumbnail of node {nid}", at_most=(w, h)),
            descriptor=descriptor, pose_gt=pose_gt,
        )
    if desc_len is None and any(n.descriptor is not None for n in m.nodes.values()):
        sizes = {n.descriptor.size for n in m.nodes.values() if n.descriptor is not None}
        if len(sizes) > 1:
            raise _Bad("the nodes' whole-image descriptors differ in length")
    if images:
        for nid, image, image_crc in con.execute("SELECT id, image" + (", image_crc" if version >= 2 else ", NULL") + " FROM node ORDER BY id"):
            if nid not in m.nodes:  # pragma: no cover - same transaction
                raise _Bad(f"node {nid} appeared while being read")
            m.nodes[nid].image = _check_image(nid, image, image_crc, version, node_sizes[nid])
    for a, b, kind_, inl, sim, flow, motion in _rows(con, "edge", version, order="a, b"):
        if a not in m.nodes or b not in m.nodes:
            raise _Bad(f"edge {a}-{b} names a node that does not exist")
        if a >= b:
            raise _Bad(f"edge {a}-{b} is not stored as a < b")
        if not (0 <= inl <= 10_000_000 and math.isfinite(sim) and 0.0 <= sim <= 1.0 and math.isfinite(flow) and flow >= 0):
            raise _Bad(f"edge {a}-{b} has out-of-range figures (inliers {inl}, similarity {sim}, flow {flow} px)")
        try:
            ek = EdgeKind(kind_)
        except ValueError:
            raise _Bad(f"edge {a}-{b} has unknown kind {kind_[:20]!r}") from None
        extra = {}
        if motion is not None:
            rm = _json(motion, f"the relative motion of edge {a}-{b}", 100_000)
            if not isinstance(rm, dict):
                raise _Bad(f"the relative motion of edge {a}-{b} is not a JSON object")
            extra["relative_motion"] = rm
        m.edges[(a, b)] = Edge(a, b, ek, inl, sim, flow, **extra)
    frames = []
    for i, (fid, s, si, src, nid, st) in enumerate(_rows(con, "frame", version, order="id")):
        if fid != i:
            raise _Bad(f"frame ids are not 0, 1, 2, ... (found {fid} at position {i})")
        if not (0 <= s <= _MAX_ID and 0 <= si <= _MAX_ID) or (sequences and s >= len(sequences)):
            raise _Bad(f"frame {fid} names build run {s} / position {si}, which the map does not have")
        if nid is not None and nid not in m.nodes:
            raise _Bad(f"frame {fid} names node {nid}, which does not exist")
        if not _STATUS.fullmatch(st) or (st != "ok" and nid is not None):
            raise _Bad(f"frame {fid} has a malformed status {st[:20]!r}")
        frames.append(FrameRecord(fid, s, si, src, nid, st))
    m.frames = frames
    arrays = {}
    for name, dt, shape, data in _rows(con, "array", version, order="name"):
        if len(name) > 256:
            raise _Bad("an array name is too long")
        arrays[name] = _unpack(data, dt, shape, f"array {name[:60]!r}")
    index_arrays = {k: v for k, v in arrays.items() if _INDEX_ARRAY.fullmatch(k)}
    if hasattr(m, "arrays"):
        m.arrays = {k: v for k, v in arrays.items() if k not in index_arrays}
    if index_arrays:
        from topomap.retrieval import BowIndex

        try:
            m.index = BowIndex.from_arrays(index_arrays, kind)
        except MapFormatError as e:
            raise _Bad(str(e).removeprefix("map ")) from None
        unknown = set(int(i) for i in m.index.node_ids) - set(m.nodes)
        if unknown:
            raise _Bad(f"its index names nodes that do not exist ({sorted(unknown)[:3]}); rebuild it with `topomap index`")
    return m


def _check_image(nid: int, image: bytes | None, image_crc, version: int, size: tuple[int, int]) -> np.ndarray | None:
    if image is None:
        if image_crc is not None:
            raise _Bad(f"node {nid} lost its image")
        return None
    if not isinstance(image, bytes):
        raise _Bad(f"the image of node {nid} holds {type(image).__name__} data, expected BLOB")
    if version >= 2 and (type(image_crc) is not int or zlib.crc32(image) != image_crc):
        raise _Bad(f"the image of node {nid} fails its checksum: the file changed after topomap wrote it")
    return _decode_blob(image, f"the image of node {nid}", exact=size)


def load_node_image(path: str | Path, node_id: int) -> np.ndarray | None:
    """The stored keyframe image of one node (``None`` if the map does not store images)."""
    path = Path(path)
    with _reading(path) as (con, version, _):
        try:
            row = con.execute("SELECT image, " + ("image_crc" if version >= 2 else "NULL") + ", width, height FROM node WHERE id = ?",
                              (int(node_id),)).fetchone()
        except (*_SQLITE_ERRORS, OverflowError) as e:
            raise _damaged(path, f"SQLite cannot read it ({e})") from None
    if row is None:
        from topomap.errors import NodeNotFoundError

        raise NodeNotFoundError(f"node {node_id} is not in map {display_name(path.name)}")
    image, image_crc, w, h = row
    if not (type(w) is int and type(h) is int and 1 <= w <= MAX_WORKING_SIDE_PX and 1 <= h <= MAX_WORKING_SIDE_PX):
        raise _damaged(path, f"node {node_id} has a malformed working size")
    try:
        return _check_image(int(node_id), image, image_crc, version, (w, h))
    except _Bad as e:
        raise _damaged(path, str(e)) from None


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
