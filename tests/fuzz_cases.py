"""Seeded generators of hostile inputs for the fuzz/fault tests (imported by tests/ and benchmarks/).

Everything a stranger, an attacker or a crashing machine hands topomap: image bombs (files that
declare huge sizes, complete or cut short), byte flips and truncations of map files, tampered rows,
views and triggers, hostile world files. Each generator is a pure function of its arguments (and a
seed where randomness enters), so a failing case can be regenerated from its name.
"""

from __future__ import annotations

import json
import random
import sqlite3
import struct
import zlib
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


def tamper(path: Path, *statements: str) -> None:
    """Run SQL statements on a map behind topomap's back, and commit."""
    con = sqlite3.connect(path)
    try:
        for sql in statements:
            con.execute(sql)
        con.commit()
    finally:
        con.close()


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
    "edge_missing_node": ("INSERT INTO edge VALUES (0, 999, 'loop', 50, 0.5, 1.0, NULL)",),
    "edge_self_loop": ("INSERT INTO edge VALUES (1, 1, 'loop', 50, 0.5, 1.0, NULL)",),
    "edge_reversed": ("INSERT INTO edge SELECT b, a, kind, inliers, similarity, flow_px, NULL FROM edge LIMIT 1",),
    "edge_motion_not_json": ("UPDATE edge SET relative_motion = '{oops'",),
    "edge_motion_blob": ("UPDATE edge SET relative_motion = x'00ff'",),
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
    "array_indptr_reversed": ("UPDATE array SET data = (SELECT data FROM array WHERE name = 'bow_indptr') WHERE name = 'bow_indptr'",),
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
def world_attacks(base: dict) -> dict[str, dict | str]:
    """Hostile variants of a world dict (``World.to_dict()``): name -> dict, or raw JSON text."""
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
                                   for i in range(206_000)]),
        "route_huge": with_(routes={"loop": {"closed": False, "waypoints": [[0.0, float(i)] for i in range(300_000)]}}),
        "seed_text": with_(seed="x"),
        "name_huge": with_(name="n" * 5_000_000),
    }
    out["nested_arrays"] = '{"format": "topomap-world", "version": 1, "walls": ' + "[" * 200_000 + "]" * 200_000 + "}"
    return out
