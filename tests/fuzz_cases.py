"""Seeded generators of hostile inputs for the fuzz/fault tests (imported by tests/ and benchmarks/).

Everything a stranger, an attacker or a crashing machine hands topomap: image bombs (files that
declare huge sizes, complete or cut short), byte flips and truncations of map files, tampered rows,
views and triggers, hostile world files. Each generator is a pure function of its arguments (and a
seed where randomness enters), so a failing case can be regenerated from its name.
"""

from __future__ import annotations

import json
import os
import random
import shutil
import signal
import sqlite3
import struct
import time
import zlib
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

__all__ = [
    "png_bomb",
    "png_declaring",
    "jpeg_declaring",
    "pgm_declaring",
    "flip_byte",
    "truncate_file",
    "TAMPERS",
    "SCHEMA_ATTACKS",
    "tamper",
    "reseal",
    "world_attacks",
]


# ---------------------------------------------------------------------- image bombs
def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def _zeros_deflate(n: int) -> bytes:
    """A zlib stream of ``n`` zero bytes, made in time proportional to its (tiny) compressed size:
    after a full flush the compressor restarts from scratch, so every 1 MiB block of zeros
    compresses to the same bytes; the Adler-32 of ``n`` zeros is ``(n mod 65521) << 16 | 1``."""
    block = 1 << 20
    c = zlib.compressobj(9, zlib.DEFLATED, 15, 9)
    head = c.compress(bytes(min(block, n))) + c.flush(zlib.Z_FULL_FLUSH)
    out = [head]
    if n > block:
        rep = c.compress(bytes(block)) + c.flush(zlib.Z_FULL_FLUSH)
        k, r = divmod(n - block, block)
        out.append(rep * k)
        if r:
            out.append(c.compress(bytes(r)) + c.flush(zlib.Z_FULL_FLUSH))
    out.append(b"\x03\x00")  # an empty final block with fixed Huffman codes
    out.append(struct.pack(">I", ((n % 65521) << 16) | 1))
    return b"".join(out)


def png_bomb(width: int, height: int, channels: int = 1) -> bytes:
    """A complete, valid PNG of ``width x height`` black pixels (about 1 KB per decoded MB)."""
    colour = {1: 0, 3: 2}[channels]
    ihdr = struct.pack(">IIBBBBB", width, height, 8, colour, 0, 0, 0)
    idat = _zeros_deflate(height * (width * channels + 1))
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", idat) + _chunk(b"IEND", b"")


def png_declaring(width: int, height: int, seed: int = 0) -> bytes:
    """A small valid PNG whose header is rewritten to declare ``width x height`` (data cut short)."""
    img = np.random.default_rng(seed).integers(0, 256, (16, 16), dtype=np.uint8)
    data = bytearray(cv2.imencode(".png", img)[1].tobytes())
    ihdr = bytes(data[12:16]) + struct.pack(">II", width, height) + bytes(data[24:29])
    data[16:24] = struct.pack(">II", width, height)
    data[29:33] = struct.pack(">I", zlib.crc32(ihdr) & 0xFFFFFFFF)
    return bytes(data)


def jpeg_declaring(width: int, height: int, seed: int = 0, colour: bool = False) -> bytes:
    """A small valid JPEG whose start-of-frame is rewritten to declare ``width x height``."""
    rng = np.random.default_rng(seed)
    img = rng.integers(0, 256, (16, 16, 3) if colour else (16, 16), dtype=np.uint8)
    data = bytearray(cv2.imencode(".jpg", img)[1].tobytes())
    i = 2
    while i + 9 < len(data):
        marker = data[i + 1]
        if marker in (0xC0, 0xC1, 0xC2):
            data[i + 5 : i + 9] = struct.pack(">HH", height, width)
            return bytes(data)
        i += 2 + int.from_bytes(data[i + 2 : i + 4], "big")
    raise AssertionError("no start-of-frame marker")  # pragma: no cover


def pgm_declaring(width: int, height: int, maxval: int = 255) -> bytes:
    """A binary PGM header declaring ``width x height`` followed by a few bytes of data."""
    return f"P5\n{width} {height}\n{maxval}\n".encode() + bytes(64)


# ---------------------------------------------------------------------- damaged files
def flip_byte(path: Path, seed: int, lo: int = 100) -> tuple[int, int]:
    """Flip one random bit pattern in one random byte at or after offset ``lo`` (past the SQLite
    header, whose damage is covered elsewhere). Returns ``(offset, xor mask)``."""
    data = bytearray(path.read_bytes())
    rng = random.Random(seed)
    off = rng.randrange(min(lo, len(data) - 1), len(data))
    mask = rng.randrange(1, 256)
    data[off] ^= mask
    path.write_bytes(bytes(data))
    return off, mask


def truncate_file(path: Path, seed: int) -> int:
    """Cut the file at a random length (keeping at least one byte). Returns the new length."""
    size = path.stat().st_size
    n = random.Random(seed).randrange(1, size)
    with open(path, "r+b") as fh:
        fh.truncate(n)
    return n


def tamper(path: Path, *statements) -> int:
    """Run SQL statements (or callables taking the connection) on a map behind topomap's back, and
    commit. Returns how many rows changed."""
    con = sqlite3.connect(path)
    try:
        for sql in statements:
            sql(con) if callable(sql) else con.execute(sql)
        con.commit()
        return con.total_changes
    finally:
        con.close()


def _rewrite_array(con: sqlite3.Connection, name: str, change) -> None:
    """Replace a named array's data by ``change(array)`` (same dtype and shape)."""
    dtype, shape, data = con.execute("SELECT dtype, shape, data FROM array WHERE name = ?", (name,)).fetchone()
    a = np.frombuffer(data, np.dtype(dtype)).reshape(json.loads(shape))
    con.execute("UPDATE array SET data = ? WHERE name = ?", (np.ascontiguousarray(change(a)).astype(a.dtype).tobytes(), name))


def reseal(path: Path) -> None:
    """Recompute every checksum and the header's row counts over the rows as they are stored: what
    an attacker who knows the format does after tampering, so the checks behind the checksums get
    tested too."""
    from topomap import store

    con = sqlite3.connect(path)
    try:
        counts = {t: con.execute(f"SELECT count(*) FROM {t}").fetchone()[0] for t in store._COLUMNS if t != "meta"}
        if con.execute("SELECT count(*) FROM meta WHERE key = 'row_counts'").fetchone()[0]:
            con.execute("UPDATE meta SET value = ? WHERE key = 'row_counts'", (json.dumps(counts),))
        for table, spec in store._COLUMNS.items():
            cols = [c for c, _, _ in spec]
            for rowid, *vals in con.execute(f"SELECT rowid, {', '.join(cols)} FROM {table}").fetchall():
                if table == "node":
                    img = vals[7]
                    image_crc = None if img is None else zlib.crc32(img if isinstance(img, bytes) else str(img).encode())
                    con.execute("UPDATE node SET image_crc = ?, crc = ? WHERE rowid = ?",
                                (image_crc, store._row_crc(vals[:7] + vals[8:] + [image_crc]), rowid))
                else:
                    con.execute(f"UPDATE {table} SET crc = ? WHERE rowid = ?", (store._row_crc(vals), rowid))
        con.commit()
    finally:
        con.close()


_EDGE = "a, b, kind, inliers, similarity, flow_px, relative_motion, crc"
#: Row tampering: name -> SQL. Each keeps the schema and corrupts values (the issue's cases first).
TAMPERS: dict[str, tuple[str, ...]] = {
    "pose_gt_brace": ("UPDATE node SET pose_gt = '{' WHERE id = 0",),
    "pose_gt_nan": ("UPDATE node SET pose_gt = '[NaN, 1, 2]' WHERE id = 0",),
    "sequences_number": ("UPDATE meta SET value = '5' WHERE key = 'sequences'",),
    "sequences_string": ("UPDATE meta SET value = '\"garbage\"' WHERE key = 'sequences'",),
    "sequences_list_of_numbers": ("UPDATE meta SET value = '[1, 2]' WHERE key = 'sequences'",),
    "meta_not_json": ("UPDATE meta SET value = '{\"fx\": ' WHERE key = 'camera'",),
    "camera_negative": ("UPDATE meta SET value = json_set(value, '$.fx', -5) WHERE key = 'camera'",),
    "build_config_garbage": ("UPDATE meta SET value = '[]' WHERE key = 'build_config'",),
    "feature_kind_other": ("UPDATE meta SET value = '\"sift\"' WHERE key = 'feature_kind'",),
    "meta_format_missing": ("DELETE FROM meta WHERE key = 'format'",),
    "meta_camera_missing": ("DELETE FROM meta WHERE key = 'camera'",),
    "descriptor_meta_garbage": ("UPDATE meta SET value = '\"garbage\"' WHERE key = 'descriptor'",),
    "descriptor_meta_bad_size": ("UPDATE meta SET value = '{\"kind\": \"thumbnail\", \"size\": [-1, 5], \"patch\": 8}' WHERE key = 'descriptor'",),
    "edge_a_text": ("UPDATE edge SET a = 'x' WHERE a = (SELECT min(a) FROM edge)",),
    "edge_inliers_text": ("UPDATE edge SET inliers = 'many'",),
    "edge_similarity_text": ("UPDATE edge SET similarity = 'high'",),
    "edge_similarity_nan": ("UPDATE edge SET similarity = 1e999 - 1e999",),
    "edge_similarity_big": ("UPDATE edge SET similarity = 1e300",),
    "edge_inliers_negative": ("UPDATE edge SET inliers = -5",),
    "edge_flow_inf": ("UPDATE edge SET flow_px = 1e999",),
    "edge_missing_node": (f"INSERT INTO edge ({_EDGE}) VALUES (0, 999, 'loop', 50, 0.5, 1.0, NULL, 0)",),
    "edge_self_loop": (f"INSERT INTO edge ({_EDGE}) VALUES (1, 1, 'loop', 50, 0.5, 1.0, NULL, 0)",),
    "edge_reversed": (f"INSERT INTO edge ({_EDGE}) SELECT b, a, kind, inliers, similarity, flow_px, NULL, 0 FROM edge LIMIT 1",),
    "edge_motion_not_json": ("UPDATE edge SET relative_motion = '{oops'",),
    "edge_motion_blob": ("UPDATE edge SET relative_motion = x'00ff'",),
    "edge_motion_not_object": ("UPDATE edge SET relative_motion = '[1, 2]'",),
    "thumbnail_empty": ("UPDATE node SET thumbnail = x'' WHERE id = 0",),
    "thumbnail_text": ("UPDATE node SET thumbnail = 'not an image' WHERE id = 0",),
    "image_text": ("UPDATE node SET image = 'not an image' WHERE id = 0",),
    "desc_shape_mismatch": ("UPDATE feature SET desc_shape = json_array(count * 2, 16)",),
    "desc_dtype_f8": ("UPDATE feature SET desc_dtype = '<f8', desc_shape = json_array(count, 4)",),
    "desc_dtype_object": ("UPDATE feature SET desc_dtype = 'O'",),
    "desc_shape_not_json": ("UPDATE feature SET desc_shape = '[1,'",),
    "desc_shape_huge": ("UPDATE feature SET desc_shape = '[100000000000, 100000000000]'",),
    "kp_dtype_f8": ("UPDATE feature SET kp_dtype = '<f8'",),
    "feature_count_wrong": ("UPDATE feature SET count = count + 1",),
    "feature_count_negative": ("UPDATE feature SET count = -1",),
    "feature_kind_row": ("UPDATE feature SET kind = 'sift'",),
    "feature_missing": ("DELETE FROM feature WHERE node_id = 1",),
    "node_descriptor_short": ("UPDATE node SET descriptor = substr(descriptor, 1, 16), descriptor_shape = '[4]' WHERE id = 0",),
    "node_descriptor_dtype": ("UPDATE node SET descriptor_dtype = '<f8', descriptor_shape = json_array(length(descriptor) / 8)",),
    "node_width_zero": ("UPDATE node SET width = 0",),
    "node_width_huge": ("UPDATE node SET width = 2000000000, height = 2000000000",),
    "node_sequence_unknown": ("UPDATE node SET sequence = 77 WHERE id = 0",),
    "node_source_blob": ("UPDATE node SET source = x'ff00' WHERE id = 0",),
    "frame_node_missing": ("UPDATE frame SET node_id = 999 WHERE id = 0",),
    "frame_id_gap": ("UPDATE frame SET id = id + 100 WHERE id = (SELECT max(id) FROM frame)",),
    "frame_status_int": ("UPDATE frame SET status = 5",),
    "frame_sequence_unknown": ("UPDATE frame SET sequence = 42",),
    "array_dtype_object": ("UPDATE array SET dtype = 'O' WHERE name = 'bow_rows'",),
    "array_shape_wrong": ("UPDATE array SET shape = '[3]' WHERE name = 'bow_rows'",),
    "array_data_short": ("UPDATE array SET data = substr(data, 1, 4) WHERE name = 'bow_indptr'",),
    "array_missing": ("DELETE FROM array WHERE name = 'bow_rows'",),
    "array_indptr_reversed": (lambda con: _rewrite_array(con, "bow_indptr", lambda a: a[::-1].copy()),),
    "array_counts_zero": (lambda con: _rewrite_array(con, "bow_counts", lambda a: np.zeros_like(a)),),
    "array_node_ids_repeated": (lambda con: _rewrite_array(con, "bow_node_ids", lambda a: np.full_like(a, a[0])),),
    "array_unknown_name_bad_dtype": ("INSERT INTO array (name, dtype, shape, data, crc) VALUES ('calib_x', '>f8', '[1]', x'0000000000000000', 0)",),
    "array_rows_out_of_range": ("UPDATE array SET data = zeroblob(length(data)) WHERE name = 'bow_node_ids'",),
    "vocab_children_out_of_range": ("UPDATE array SET data = randomblob(length(data)) WHERE name = 'vocab_children_1'",),
}

#: Schema attacks: name -> SQL. Views, triggers, virtual tables, extra or missing tables/columns.
SCHEMA_ATTACKS: dict[str, tuple[str, ...]] = {
    "recursive_view_frame": (
        "ALTER TABLE frame RENAME TO frame_old",
        "CREATE VIEW frame AS WITH RECURSIVE c(x) AS (SELECT 0 UNION ALL SELECT x + 1 FROM c) "
        "SELECT x AS id, 0 AS sequence, x AS seq_index, 'a' AS source, NULL AS node_id, 'ok' AS status FROM c",
    ),
    "recursive_view_meta": (
        "ALTER TABLE meta RENAME TO meta_old",
        "CREATE VIEW meta AS SELECT * FROM meta_old UNION ALL SELECT * FROM ("
        "WITH RECURSIVE c(x) AS (SELECT 0 UNION ALL SELECT x + 1 FROM c) SELECT 'k' || x, '1' FROM c)",
    ),
    "trigger": ("CREATE TRIGGER t AFTER INSERT ON node BEGIN DELETE FROM edge; END",),
    "extra_table": ("CREATE TABLE extra (x)",),
    "extra_index": ("CREATE INDEX edge_kind ON edge(kind)",),
    "extra_view": ("CREATE VIEW v AS SELECT 1",),
    "virtual_table": ("CREATE VIRTUAL TABLE vt USING rtree(id, x0, x1)",),
    "missing_table": ("DROP TABLE array",),
    "extra_column": ("ALTER TABLE edge ADD COLUMN extra INTEGER",),
    "dropped_index": ("DROP INDEX frame_node",),
    "renamed_column": ("ALTER TABLE frame RENAME COLUMN status TO state",),
    "edge_without_constraints": (
        "CREATE TABLE edge2 (a, b, kind, inliers, similarity, flow_px, relative_motion)",
        "INSERT INTO edge2 SELECT a, b, kind, NULL, NULL, NULL, NULL FROM edge",
        "DROP TABLE edge",
        "ALTER TABLE edge2 RENAME TO edge",
    ),
}


# ---------------------------------------------------------------------- hostile worlds
def world_attacks(base: dict, many: int = 6000) -> dict[str, dict | str]:
    """Hostile variants of a world dict (``World.to_dict()``): name -> dict, or raw JSON text.
    ``many``: walls of the "many walls" world (the issue's had 206,000; the limit is 5,000)."""
    def with_(**kv):
        d = json.loads(json.dumps(base))
        d.update(kv)
        return d

    walls = base["walls"]
    w0 = walls[0]
    out: dict[str, dict | str] = {
        "floor_texture_negative_seed": with_(floor_texture="proc:tiles:-5"),
        "texture_escape": with_(walls=[[*w[:4], "user:../../other/x.jpg"] for w in walls], texture_dir="/tmp"),
        "texture_absolute": with_(walls=[[*w[:4], "user:/etc/passwd"] for w in walls], texture_dir="/tmp"),
        "marker_colour_huge": with_(markers=[{"x": 1.0, "z": 1.0, "height_m": 1.0, "color": [1e30, 0, 0]}]),
        "marker_radius_inf": with_(markers=[{"x": 1.0, "z": 1.0, "height_m": 1.0, "radius_m": 1e999}]),
        "wall_height_huge": with_(wall_height_m=1e300),
        "walls_not_list": with_(walls={"a": 1}),
        "wall_short_row": with_(walls=[[1, 2, 3]]),
        "many_walls": with_(walls=[[float(i % 500), float(i // 500), float(i % 500) + 0.5, float(i // 500), w0[4]]
                                   for i in range(many)]),
        "route_huge": with_(routes={"loop": {"closed": False, "waypoints": [[0.0, float(i)] for i in range(2 * many)]}}),
        "seed_text": with_(seed="x"),
        "name_huge": with_(name="n" * 10_000),
        "tile_variants_huge": with_(tile_variants=10**9),
        "free_floor_huge": with_(free=[[0.0, 0.0, 9000.0, 9000.0]]),  # 81 M cells for the renderer to cut
    }
    out["nested_arrays"] = '{"format": "topomap-world", "version": 1, "walls": ' + "[" * 200_000 + "]" * 200_000 + "}"
    return out


# ---------------------------------------------------------------------- the cases, as functions
# Each case kind is ``kind(ctx, seed) -> outcome``: "clean error" (a TopomapError of one line),
# "success" (the operation worked and nothing was lost or silently changed), or a string starting
# with "data loss" / "silent" saying what went wrong; ": detail" may follow. Any other exception
# escapes: a traceback.
OK, ERROR = "success", "clean error"


@dataclass
class FuzzContext:
    """What every case starts from: ``base`` a small valid map (current schema, index, stored
    images), ``query`` an image of its place, ``work`` a scratch folder, ``signature`` the base
    map's content (:func:`map_signature`), ``grow_from`` an image folder for appends."""

    base: Path
    query: np.ndarray
    work: Path
    signature: tuple
    grow_from: Path


def make_base_map(folder: Path) -> Path:
    """A small map (5 synthetic frames of 240x180, ORB, a two-level vocabulary, images stored)."""
    from map_synth import scene, window, write_sequence
    from topomap.build import build_map
    from topomap.config import BuildConfig, FeatureConfig
    from topomap.store import save_map

    tex = scene(3)
    frames = folder / "frames"
    write_sequence(frames, [window(tex, 50.0 * i, y=20.0, size=(240, 180)) for i in range(5)])
    grow = folder / "grow"
    write_sequence(grow, [window(tex, 50.0 * i + 20.0, y=30.0, size=(240, 180)) for i in range(3)], stem="g")
    cfg = BuildConfig(features=FeatureConfig(max_features=150, upscale_min_px=240), vocabulary_words=100,
                      thumbnail_px=64, keyframe_min_inliers=400)  # every frame a node; a 2-level vocabulary
    return save_map(build_map(frames, cfg), folder / "base.topomap")


def map_signature(m) -> tuple:
    """Everything a map holds, as comparable bytes (images included when loaded)."""
    nodes = tuple(
        (n.id, n.sequence, n.frame_id, n.source, n.features.kind, n.features.image_size,
         n.features.keypoints.tobytes(), n.features.descriptors.tobytes(), n.thumbnail.tobytes(),
         None if n.image is None else n.image.tobytes(), None if n.descriptor is None else n.descriptor.tobytes(),
         n.pose_gt)
        for n in sorted(m.nodes.values(), key=lambda n: n.id))
    index = None if m.index is None else tuple(sorted((k, v.dtype.str, v.shape, v.tobytes()) for k, v in m.index.to_arrays().items()))
    meta = json.dumps({k: v for k, v in m.meta.items() if k not in ("revision",)}, sort_keys=True, default=str)
    arrays = tuple(sorted((k, v.dtype.str, v.shape, v.tobytes()) for k, v in getattr(m, "arrays", {}).items()))
    return (nodes, tuple(sorted(m.edges.items())), tuple(m.frames), json.dumps(m.sequences, sort_keys=True),
            m.camera, m.config, index, meta, arrays)


def exercise(path: Path, query: np.ndarray):
    """What the commands do with a map: load it (images too), localize, plan, export, read an image."""
    from topomap.errors import NoRouteError
    from topomap.localize import Localizer
    from topomap.plan import Planner
    from topomap.store import export_json, load_map, load_node_image

    m = load_map(path, images=True)
    Localizer(m).localize(query)
    ids = sorted(m.nodes)
    try:
        Planner(m).route(ids[0], ids[-1])
    except NoRouteError:
        pass
    json.dumps(export_json(m))
    load_node_image(path, ids[0])
    return m


def _copy(ctx: FuzzContext, name: str) -> Path:
    dst = ctx.work / name
    shutil.copyfile(ctx.base, dst)
    return dst


def _opens_unchanged(ctx: FuzzContext, path: Path) -> str:
    from topomap.errors import TopomapError

    try:
        m = exercise(path, ctx.query)
    except TopomapError as e:
        if "\n" in str(e):
            return "silent: an error message of several lines"
        return ERROR
    return OK if map_signature(m) == ctx.signature else "silent corruption: the map opened with different content"


def case_flip(ctx: FuzzContext, seed: int) -> str:
    """One byte flipped: 10% in the SQLite header, 45% in the first 8 KB (b-tree and schema
    pages), 45% anywhere."""
    p = _copy(ctx, f"flip{seed}.topomap")
    data = bytearray(p.read_bytes())
    rng = random.Random(seed)
    r = rng.random()
    lo, hi = (16, 100) if r < 0.1 else (100, min(len(data), 8192)) if r < 0.55 else (100, len(data))
    data[rng.randrange(lo, hi)] ^= rng.randrange(1, 256)
    p.write_bytes(bytes(data))
    return _opens_unchanged(ctx, p)


def case_truncate(ctx: FuzzContext, seed: int) -> str:
    p = _copy(ctx, f"cut{seed}.topomap")
    truncate_file(p, seed)
    return _opens_unchanged(ctx, p)


def case_tamper(ctx: FuzzContext, seed: int) -> str:
    """A tampered row; with an odd seed the checksums are recomputed (an attacker knows the format)."""
    names = sorted(TAMPERS)
    name = names[seed % len(names)]
    p = _copy(ctx, f"tamper{seed}.topomap")
    try:
        if tamper(p, *TAMPERS[name]) == 0:
            return _opens_unchanged(ctx, p)  # nothing to tamper with in this map (e.g. no such array)
    except sqlite3.IntegrityError:
        return ERROR  # the schema's own constraints refused it: nothing to read
    if (seed // len(names)) % 2 == 0:
        reseal(p)
    out = _opens_unchanged(ctx, p)
    return out if out != OK else f"silent: tamper {name} was not noticed"


def case_schema(ctx: FuzzContext, seed: int) -> str:
    names = sorted(SCHEMA_ATTACKS)
    name = names[seed % len(names)]
    p = _copy(ctx, f"schema{seed}.topomap")
    tamper(p, *SCHEMA_ATTACKS[name])
    out = _opens_unchanged(ctx, p)
    return out if out != OK else f"silent: schema change {name} was not noticed"


def _bomb(seed: int) -> tuple[str, bytes]:
    kinds = ("png", "png_declared", "jpeg", "jpeg_colour", "pgm", "bmp", "tiff")
    kind = kinds[seed % len(kinds)]
    rng = random.Random(seed)
    w, h = rng.choice([(30000, 30000), (60000, 60000), (65535, 1000), (20000, 20000), (9000, 9000)])
    if kind == "png":
        return kind, png_bomb(w, h) if w * h <= 1_000_000_000 else png_declaring(w, h, seed)
    if kind == "png_declared":
        return kind, png_declaring(w, h, seed)
    if kind in ("jpeg", "jpeg_colour"):
        return kind, jpeg_declaring(min(w, 65535), min(h, 65535), seed, colour=kind == "jpeg_colour")
    if kind == "pgm":
        return kind, pgm_declaring(w, h)
    if kind == "bmp":
        return kind, b"BM" + struct.pack("<IHHI", 54, 0, 0, 54) + struct.pack("<IiiHHIIiiII", 40, w, h, 1, 24, 0, 0, 0, 0, 0, 0)
    return kind, b"II*\x00" + struct.pack("<I", 8) + struct.pack("<H", 3) + struct.pack("<HHII", 256, 4, 1, w) \
        + struct.pack("<HHII", 257, 4, 1, h) + struct.pack("<HHII", 258, 3, 1, 8) + b"\x00\x00\x00\x00"


def case_image_bomb(ctx: FuzzContext, seed: int) -> str:
    """An image declaring far more pixels than it holds, as a file to build from and as bytes."""
    from topomap.errors import DatasetError
    from topomap.images import decode_image, read_image

    kind, data = _bomb(seed)
    try:
        decode_image(data)
        return f"silent: a {kind} bomb was decoded"
    except DatasetError:
        pass
    f = ctx.work / f"bomb{seed}.{ {'png_declared': 'png', 'jpeg_colour': 'jpg', 'jpeg': 'jpg', 'tiff': 'tif'}.get(kind, kind)}"
    f.write_bytes(data)
    try:
        read_image(f)
        return f"silent: a {kind} bomb file was decoded"
    except DatasetError:
        return ERROR


def case_map_bomb(ctx: FuzzContext, seed: int) -> str:
    """A node's thumbnail or image replaced by a bomb (checksums recomputed)."""
    kind, data = _bomb(seed)
    p = _copy(ctx, f"mapbomb{seed}.topomap")
    col = "thumbnail" if seed % 2 == 0 else "image"
    con = sqlite3.connect(p)
    con.execute(f"UPDATE node SET {col} = ? WHERE id = (SELECT min(id) FROM node)", (data,))
    con.commit()
    con.close()
    reseal(p)
    return _opens_unchanged(ctx, p)


def _grow(m, tag: str, k: int):
    """Add ``k`` nodes (copies of the first ones, new ids), their frames and a build-run record
    tagged ``tag`` to map ``m``, as an append would."""
    from dataclasses import replace

    from topomap.graph import Edge, EdgeKind, FrameRecord

    seq = len(m.sequences)
    first, f0 = m.next_node_id(), len(m.frames)
    olds = sorted(m.nodes.values(), key=lambda n: n.id)
    for i in range(k):
        src = olds[i % len(olds)]
        n = replace(src, id=first + i, sequence=seq, frame_id=f0 + i, source=f"{tag}_{i}.png")
        m.add_node(n)
        m.frames.append(FrameRecord(f0 + i, seq, i, n.source, n.id))
        if i:
            m.add_edge(Edge(first + i - 1, first + i, EdgeKind.SEQUENTIAL, 40, 0.5, 3.0))
    m.add_edge(Edge(olds[0].id, first, EdgeKind.LOOP, 30, 0.4, 5.0))
    m.sequences.append({"source": tag, "kind": "folder", "frames": k})
    from topomap.build import build_index

    build_index(m)
    return m


def _fork(fn) -> int:
    """Run ``fn()`` in a forked child that exits with its return value (never returns there)."""
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child
        code = 1
        try:
            code = fn()
        except BaseException:  # noqa: BLE001 - any failure of the child is its exit code
            code = 1
        finally:
            os._exit(code)
    return pid


def case_kill_commit(ctx: FuzzContext, seed: int) -> str:
    """A writer killed with SIGKILL at a random moment of its update's commit (its page cache is
    tiny, so pages reach the file before the commit and a hot journal is left behind). Afterwards
    the map must open as exactly the old or exactly the new map, and take the next write."""
    from topomap import store
    from topomap.store import load_map, open_for_update

    p = _copy(ctx, f"kill{seed}.topomap")
    rng = random.Random(seed)
    r, w = os.pipe()

    def child() -> int:
        os.close(r)
        configure = store._configure

        def small_cache(con, *, readonly):
            configure(con, readonly=readonly)
            con.execute("PRAGMA cache_size = 2")

        store._configure = small_cache
        with open_for_update(p) as u:
            _grow(u.map, f"killed{seed}", 4)
            os.write(w, b"g")
            u.commit()
        return 0

    pid = _fork(child)
    os.close(w)
    os.read(r, 1)
    os.close(r)
    time.sleep(rng.uniform(0.0, 0.08))
    try:
        os.kill(pid, signal.SIGKILL)
    except ProcessLookupError:  # pragma: no cover
        pass
    _, status = os.waitpid(pid, 0)
    finished = os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0
    if os.WIFEXITED(status) and os.WEXITSTATUS(status) != 0:
        return "traceback: the writer failed before it was killed"
    journal = store._companion(p, "-journal")
    hot = journal.exists() and journal.stat().st_size > 0
    m = exercise(p, ctx.query)  # recovers the hot journal without user action
    grown = len(m.nodes) - len(ctx.signature[0])
    tags = [s.get("source") for s in m.sequences]
    if grown == 0 and map_signature(m) == ctx.signature:
        state = "old"
    elif grown == 4 and tags[-1] == f"killed{seed}":
        state = "new"
    else:
        return f"data loss: a partial update survived the kill ({grown} new nodes, runs {tags})"
    if finished and state == "old":
        return "data loss: a committed update vanished"
    if journal.exists():
        return "data loss: the hot journal was left beside the map"
    with open_for_update(p) as u:  # the next writer works
        _grow(u.map, "after", 1)
        u.commit()
    return f"{OK}: {state} map, {'a hot journal rolled back' if hot else 'no journal left'}"


def case_concurrent(ctx: FuzzContext, seed: int) -> str:
    """2-4 writers grow the same map at once. Every writer that reports success must find its run
    in the map afterwards; the others are refused with MapConflictError."""
    from topomap.errors import MapConflictError
    from topomap.store import load_map, open_for_update, update_map

    p = _copy(ctx, f"conc{seed}.topomap")
    rng = random.Random(seed)
    n = rng.randint(2, 4)
    stale = rng.random() < 0.3  # one of them updates a map it loaded before the others wrote

    def writer(i: int):
        def run() -> int:
            time.sleep(rng.uniform(0, 0.05) * i)
            try:
                if stale and i == 0:
                    m = load_map(p)
                    time.sleep(0.3)
                    n0, f0 = m.next_node_id(), len(m.frames)
                    update_map(_grow(m, f"w{i}", 1), p, first_new_node=n0, first_new_frame=f0)
                else:
                    with open_for_update(p, timeout_s=20) as u:
                        _grow(u.map, f"w{i}", 1)
                        u.commit()
            except MapConflictError:
                return 3
            return 0
        return run

    pids = [_fork(writer(i)) for i in range(n)]
    codes = [os.WEXITSTATUS(os.waitpid(pid, 0)[1]) for pid in pids]
    if any(c not in (0, 3) for c in codes):
        return "traceback: a writer failed with an unexpected error"
    m = load_map(p)
    runs = [s.get("source") for s in m.sequences]
    lost = [f"w{i}" for i, c in enumerate(codes) if c == 0 and f"w{i}" not in runs]
    if lost:
        return f"data loss: writers {lost} reported success but their runs are missing ({runs})"
    if len(set(n.sequence for n in m.nodes.values())) != len(runs) or m.index is None \
            or set(int(i) for i in m.index.node_ids) != set(m.nodes):
        return "data loss: the map's runs, nodes and index disagree"
    return OK if 0 in codes else "data loss: no writer succeeded"


def case_world(ctx: FuzzContext, seed: int) -> str:
    """A hostile world file (too big, too many walls, bad numbers, textures out of their folder)."""
    from topomap.errors import TopomapError
    from topomap.sim.world import load_world

    attacks = world_attack_set()
    names = sorted(attacks) + ["sparse_2gb", "dev_zero", "fifo"]
    name = names[seed % len(names)]
    f = ctx.work / f"world{seed}.json"
    if name == "sparse_2gb":
        with open(f, "wb") as fh:
            fh.truncate(2 << 30)
    elif name == "dev_zero":
        f = Path("/dev/zero")
    elif name == "fifo":
        os.mkfifo(f)
    else:
        w = attacks[name]
        f.write_text(w if isinstance(w, str) else json.dumps(w))
    try:
        load_world(f)
    except TopomapError:
        return ERROR
    return f"silent: world attack {name} loaded"


_WORLD_ATTACKS: dict | None = None


def world_attack_set() -> dict:
    """:func:`world_attacks` of the default world, made once per process (the big ones take a while)."""
    global _WORLD_ATTACKS
    if _WORLD_ATTACKS is None:
        from topomap.sim.world import default_world

        _WORLD_ATTACKS = world_attacks(default_world().to_dict())
    return _WORLD_ATTACKS


def case_inputs(ctx: FuzzContext, seed: int) -> str:
    """A build folder (or list file) with entries that are not images: a folder named x.jpg, a FIFO,
    a link to /dev/zero, a link loop, an empty file, a declared bomb. The build must finish, with
    every such entry counted as skipped."""
    from topomap.build import build_map
    from topomap.config import BuildConfig, FeatureConfig
    from topomap.images import open_sequence

    rng = random.Random(seed)
    d = ctx.work / f"inputs{seed}"
    d.mkdir()
    good = sorted(ctx.grow_from.iterdir())
    for g in good:
        shutil.copy(g, d / g.name)
    odd = rng.sample(["dir", "fifo", "zero", "loop", "empty", "bomb", "broken"], rng.randint(1, 4))
    for k in odd:
        name = d / f"odd_{k}.png"
        if k == "dir":
            name.mkdir()
        elif k == "fifo":
            os.mkfifo(name)
        elif k == "zero":
            os.symlink("/dev/zero", name)
        elif k == "loop":
            os.symlink(name.name, name)
        elif k == "empty":
            name.write_bytes(b"")
        elif k == "bomb":
            name.write_bytes(png_declaring(40000, 40000))
        else:
            os.symlink("missing.png", name)
    source = d
    if rng.random() < 0.5:  # the same entries through a list file
        source = d / "list.txt"
        source.write_text("\n".join(str(x) for x in sorted(d.iterdir()) if x.name != "list.txt") + "\n")
    cfg = BuildConfig(features=FeatureConfig(max_features=150, upscale_min_px=240), vocabulary_words=32)
    m = build_map(open_sequence(source), cfg)
    run = m.sequences[-1]
    if run["frames_skipped"] != len(odd) or run["frames_read"] != len(good):
        return f"silent: {run['frames_skipped']} of {len(odd)} odd entries counted as skipped"
    return OK


#: kind -> case function. The tests run a few hundred of these, the benchmark thousands.
CASE_KINDS = {
    "flip": case_flip,
    "truncate": case_truncate,
    "tamper": case_tamper,
    "schema": case_schema,
    "image_bomb": case_image_bomb,
    "map_bomb": case_map_bomb,
    "kill_commit": case_kill_commit,
    "concurrent": case_concurrent,
    "world": case_world,
    "inputs": case_inputs,
}
