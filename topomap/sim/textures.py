"""Wall, floor and ceiling textures: real photographs plus procedural variety.

A texture is named by a string key that a world file stores:

* ``photo:NAME`` — one of the photographs shipped in ``topomap_datasets/textures`` (crops of the
  real castle-P30 images, see PROVENANCE.md there);
* ``user:FILE`` — a photograph in the folder the user gave with ``--textures DIR``;
* either of them with ``:flip`` appended — the photograph mirrored left-right (binary descriptors
  such as ORB are not mirror invariant, so it adds a distinct texture that still looks alike);
* ``proc:KIND:SEED`` — drawn procedurally from a seed (kinds in :data:`PROCEDURAL`).

Photographs make local features plentiful; overlapping crops of the same facades and procedural
patterns of one style make places look alike, as they do in real buildings. Every texture comes back
as an ``(H, W, 3) uint8`` RGB array; the same key always gives the same pixels.
"""

from __future__ import annotations

import functools
import logging
import re
from collections.abc import Callable
from importlib import resources
from pathlib import Path

import cv2
import numpy as np

from topomap.errors import DatasetError, unknown_choice

__all__ = [
    "PROCEDURAL",
    "IMAGE_SUFFIXES",
    "builtin_texture_dir",
    "photo_keys",
    "texture_image",
    "check_texture_key",
    "texture_width_m",
    "FLOOR_TILE_M",
    "texture_variant",
    "CEILING_TILE_M",
]

log = logging.getLogger(__name__)

#: Files accepted as photographs in a texture folder.
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp")
#: Side of the square patch of floor one floor texture covers [m].
FLOOR_TILE_M = 2.0
#: Side of the square patch of ceiling one ceiling texture covers [m].
CEILING_TILE_M = 2.4

_PROC_PX = 256  # side of a procedural texture [px]


def builtin_texture_dir() -> Path:
    """Folder of the photographs shipped with topomap."""
    return Path(str(resources.files("topomap_datasets") / "textures"))


def _photo_files(folder: Path) -> list[Path]:
    if not folder.is_dir():
        raise DatasetError(f"texture folder {folder} does not exist; give a folder of photographs (.jpg/.png)")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
    if not files:
        raise DatasetError(f"texture folder {folder} holds no .jpg/.png photographs; add some or omit --textures")
    return files


def photo_keys(texture_dir: str | Path | None = None) -> list[str]:
    """Keys of the available photographs: the user's folder if given, else the shipped set (sorted)."""
    if texture_dir is None:
        return [f"photo:{p.stem}" for p in _photo_files(builtin_texture_dir())]
    keys = []
    for p in _photo_files(Path(texture_dir)):
        try:
            _read_photo(str(p))
        except DatasetError as e:
            log.warning("skipping a texture photograph: %s", e)
            continue
        keys.append(f"user:{p.name}")
    if not keys:
        raise DatasetError(f"no readable photograph in texture folder {texture_dir}; use .jpg/.png files")
    return keys


#: Largest photograph decoded as a texture [pixels] (a 48 MP phone photo); it is shrunk to 512 px.
MAX_PHOTO_PIXELS = 50_000_000


@functools.lru_cache(maxsize=64)
def _read_photo(path: str) -> np.ndarray:
    """A photograph as ``(H, W, 3) uint8`` RGB, longest side at most 512 px; raises :class:`DatasetError`."""
    from topomap.images import decode_image, read_file_bytes

    # through the image gate: a photograph declaring 30000 x 30000 px is refused undecoded
    img = decode_image(read_file_bytes(path, what="texture photograph"), max_pixels=MAX_PHOTO_PIXELS, color=True,
                       what=f"texture photograph {Path(path).name}")
    if img.shape[0] < 8 or img.shape[1] < 8:
        raise DatasetError(f"texture photograph {Path(path).name} is smaller than 8x8 px")
    # Large user photographs are shrunk: TinyRenderer samples textures without filtering anyway.
    scale = 512.0 / max(img.shape[:2])
    if scale < 1.0:
        img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    img.setflags(write=False)
    return img


_BARE_NAME = re.compile(r"[^/\\\x00]+")


def check_texture_key(key: str) -> None:
    """Raise :class:`DatasetError` unless ``key`` is a well-formed texture key: ``photo:NAME`` and
    ``user:FILE`` name a file directly inside their folder (no path, no ``..``), ``proc:KIND:SEED``
    a known kind and a seed from 0 to 2**63 - 1."""
    if not isinstance(key, str) or len(key) > 300:
        raise DatasetError(f"texture key {str(key)[:40]!r} is not a short text")
    kind, _, rest = key.partition(":")
    if kind in ("photo", "user"):
        name = rest[: -len(":flip")] if rest.endswith(":flip") else rest
        if not _BARE_NAME.fullmatch(name) or name in (".", ".."):
            raise DatasetError(f"texture key {key[:60]!r} must name a file inside its texture folder, without a path")
        return
    if kind == "proc":
        name, _, seed = rest.partition(":")
        if name not in PROCEDURAL:
            raise unknown_choice("procedural texture", name, PROCEDURAL)
        if not seed.isdigit() or int(seed) >= 2**63:
            raise DatasetError(f"texture key {key[:60]!r} needs a seed from 0 to 2**63 - 1, like 'proc:{name}:3'")
        return
    raise DatasetError(f"texture key {key[:60]!r} is not of the form photo:NAME[:flip], user:FILE[:flip] or proc:KIND:SEED")


def texture_image(key: str, texture_dir: str | Path | None = None) -> np.ndarray:
    """The ``(H, W, 3) uint8`` RGB pixels of texture ``key`` (read-only array)."""
    check_texture_key(key)
    kind, _, rest = str(key).partition(":")
    if kind in ("photo", "user") and rest.endswith(":flip"):
        img = texture_image(f"{kind}:{rest[: -len(':flip')]}", texture_dir)[:, ::-1]
        img = np.ascontiguousarray(img)
        img.setflags(write=False)
        return img
    if kind == "photo":
        path = builtin_texture_dir() / f"{rest}.jpg"
        if not path.is_file():
            raise DatasetError(f"texture {key!r} is not among the shipped photographs; reinstall topomap or regenerate the world")
        return _read_photo(str(path))
    if kind == "user":
        if texture_dir is None:
            raise DatasetError(f"texture {key!r} needs the user's texture folder; give --textures DIR")
        path = Path(texture_dir) / rest
        if not path.is_file():
            raise DatasetError(f"texture photograph {path} is missing; restore it or regenerate the world")
        return _read_photo(str(path))
    if kind == "proc":
        name, _, seed = rest.partition(":")
        if name not in PROCEDURAL:
            raise unknown_choice("procedural texture", name, PROCEDURAL)
        try:
            seed_i = int(seed)
        except ValueError:
            raise DatasetError(f"texture key {key!r} needs an integer seed, like 'proc:{name}:3'") from None
        return _procedural(name, seed_i)
    raise DatasetError(f"texture key {key!r} is not of the form photo:NAME[:flip], user:FILE[:flip] or proc:KIND:SEED")


def texture_variant(key: str, k: int, texture_dir: str | Path | None = None) -> np.ndarray:
    """Variant ``k`` of texture ``key`` (0: the texture itself): a procedural texture drawn again from
    another random stream of the same kind and seed; a photograph turned and mirrored (the eight
    symmetries of a square, then again). Floors and ceilings tile variants so that they never repeat
    pixel for pixel (:attr:`topomap.sim.world.World.tile_variants`)."""
    k = int(k)
    if k == 0:
        return texture_image(key, texture_dir)
    check_texture_key(key)
    kind, _, rest = str(key).partition(":")
    if kind == "proc":
        name, _, seed = rest.partition(":")
        return _procedural(name, int(seed), k)
    img = texture_image(key, texture_dir)
    img = np.rot90(img, k % 4)
    img = np.ascontiguousarray(img[:, ::-1] if (k // 4) % 2 else img)
    img.setflags(write=False)
    return img


def texture_width_m(key: str, texture_dir: str | Path | None, height_m: float) -> float:
    """Width [m] one copy of a wall texture spans when its height is stretched to ``height_m``."""
    img = texture_image(key, texture_dir)
    return height_m * img.shape[1] / img.shape[0]


# ---------------------------------------------------------------------- procedural textures
# Hand-written with numpy/OpenCV drawing: no library ships seeded, feature-rich wall patterns.
def _noise(rng: np.random.Generator, img: np.ndarray, sigma: float) -> np.ndarray:
    out = img.astype(np.float32) + rng.normal(0.0, sigma, img.shape).astype(np.float32)
    return np.clip(out, 0, 255).astype(np.uint8)


def _colour(rng: np.random.Generator, lo: int = 30, hi: int = 230) -> tuple[int, int, int]:
    return tuple(int(c) for c in rng.integers(lo, hi, 3))


def _scribble(rng: np.random.Generator, img: np.ndarray, x0: int, y0: int, x1: int, y1: int, colour) -> None:
    """Lines of random letters, like text on a notice."""
    letters = "ABCDEFGHKLMNPRSTUVWXYZ0123456789"
    y = y0 + 12
    while y < y1 - 2:
        n = max(1, (x1 - x0) // 9)
        text = "".join(rng.choice(list(letters), n))
        cv2.putText(img, text, (x0 + 2, y), cv2.FONT_HERSHEY_SIMPLEX, 0.35, colour, 1, cv2.LINE_AA)
        y += int(rng.integers(12, 18))


def _poster(rng: np.random.Generator) -> np.ndarray:
    s = _PROC_PX
    img = np.full((s, s, 3), _colour(rng, 150, 240), np.uint8)
    for _ in range(int(rng.integers(5, 10))):  # framed pictures and notices
        w, h = (int(v) for v in rng.integers(30, 110, 2))
        x, y = int(rng.integers(0, s - w)), int(rng.integers(0, s - h))
        cv2.rectangle(img, (x, y), (x + w, y + h), _colour(rng), -1)
        cv2.rectangle(img, (x, y), (x + w, y + h), _colour(rng, 0, 80), 2)
        if rng.random() < 0.6:
            _scribble(rng, img, x + 2, y + 2, x + w - 2, y + h - 2, _colour(rng, 0, 120))
    for _ in range(int(rng.integers(3, 7))):
        c = (int(rng.integers(10, s - 10)), int(rng.integers(10, s - 10)))
        cv2.circle(img, c, int(rng.integers(6, 28)), _colour(rng), -1)
    for _ in range(int(rng.integers(2, 5))):
        p = [(int(rng.integers(0, s)), int(rng.integers(0, s))) for _ in range(3)]
        cv2.fillPoly(img, [np.array(p, np.int32)], _colour(rng))
    return _noise(rng, img, 6.0)


def _bricks(rng: np.random.Generator) -> np.ndarray:
    s = _PROC_PX
    mortar = np.array(_colour(rng, 170, 220), np.float32)
    base = np.array([rng.integers(120, 190), rng.integers(50, 100), rng.integers(30, 80)], np.float32)
    img = np.empty((s, s, 3), np.float32)
    img[:] = mortar
    bh, bw = 16, 48
    for row in range(s // bh):
        off = (bw // 2) * (row % 2)
        for x in range(-bw, s, bw):
            c = np.clip(base + rng.normal(0, 18, 3), 0, 255)
            x0, x1 = max(0, x + off + 2), min(s, x + off + bw - 2)
            if x1 > x0:
                img[row * bh + 2 : row * bh + bh - 2, x0:x1] = c
    return _noise(rng, img, 10.0)


def _board(rng: np.random.Generator) -> np.ndarray:
    s = _PROC_PX
    cork = np.array([rng.integers(150, 190), rng.integers(110, 140), rng.integers(60, 90)], np.uint8)
    img = np.empty((s, s, 3), np.uint8)
    img[:] = cork
    img = _noise(rng, img, 18.0)
    cv2.rectangle(img, (0, 0), (s - 1, s - 1), _colour(rng, 40, 100), 8)
    for _ in range(int(rng.integers(6, 12))):  # pinned notes
        w, h = (int(v) for v in rng.integers(28, 70, 2))
        x, y = int(rng.integers(10, s - w - 10)), int(rng.integers(10, s - h - 10))
        paper = _colour(rng, 200, 255)
        cv2.rectangle(img, (x, y), (x + w, y + h), paper, -1)
        _scribble(rng, img, x, y, x + w, y + h, _colour(rng, 0, 90))
        cv2.circle(img, (x + w // 2, y + 4), 3, _colour(rng, 0, 255), -1)
    return img


def _panels(rng: np.random.Generator) -> np.ndarray:
    s = _PROC_PX
    base = np.array([rng.integers(120, 200), rng.integers(80, 140), rng.integers(40, 90)], np.float32)
    x = np.arange(s, dtype=np.float32)
    grain = 14.0 * np.sin(x[None, :] / rng.uniform(2.0, 5.0) + rng.uniform(0, 6.28)) + rng.normal(0, 6, (s, s))
    img = base[None, None, :] + grain[:, :, None]
    for xb in range(0, s, int(rng.integers(40, 70))):  # panel joints
        img[:, xb : xb + 2] *= 0.5
    img = np.clip(img, 0, 255).astype(np.uint8)
    # A door with frame, handle and sign.
    dw = int(rng.integers(70, 110))
    dx = int(rng.integers(10, s - dw - 10))
    cv2.rectangle(img, (dx, 40), (dx + dw, s - 1), _colour(rng), -1)
    cv2.rectangle(img, (dx, 40), (dx + dw, s - 1), (30, 30, 30), 4)
    cv2.circle(img, (dx + dw - 14, 160), 5, (220, 220, 200), -1)
    cv2.rectangle(img, (dx + 15, 60), (dx + dw - 15, 85), (240, 240, 240), -1)
    _scribble(rng, img, dx + 15, 60, dx + dw - 15, 85, (20, 20, 20))
    return _noise(rng, img, 5.0)


def _tiles(rng: np.random.Generator, detail: np.random.Generator | None = None) -> np.ndarray:
    """Floor: 4 x 4 tiles of 0.5 m with grout, tint and speckles (features near the robot). ``detail``
    draws all but the base colour (a variant of the same floor: :func:`texture_variant`)."""
    s = _PROC_PX
    n = 4
    t = s // n
    base = np.array(_colour(rng, 90, 170), np.float32)
    rng = rng if detail is None else detail
    img = np.empty((s, s, 3), np.float32)
    for i in range(n):
        for j in range(n):
            img[i * t : (i + 1) * t, j * t : (j + 1) * t] = np.clip(base + rng.normal(0, 12, 3), 0, 255)
    img = _noise(rng, img, 12.0)
    k = int(s * s * 0.01)  # speckles
    ys, xs = rng.integers(0, s, k), rng.integers(0, s, k)
    img[ys, xs] = rng.integers(0, 255, (k, 1)).astype(np.uint8)
    for _ in range(int(rng.integers(4, 9))):  # scuffs
        c = (int(rng.integers(0, s)), int(rng.integers(0, s)))
        cv2.ellipse(img, c, (int(rng.integers(3, 12)), int(rng.integers(2, 6))), float(rng.uniform(0, 180)), 0, 360, _colour(rng, 20, 90), -1)
    for i in range(n):  # grout
        img[i * t : i * t + 3, :] = 60
        img[:, i * t : i * t + 3] = 60
    return img


def _ceiling(rng: np.random.Generator, detail: np.random.Generator | None = None) -> np.ndarray:
    """Ceiling: 4 x 4 acoustic tiles of 0.6 m, perforated, with one light panel (``detail``: as :func:`_tiles`)."""
    s = _PROC_PX
    n = 4
    t = s // n
    img = np.full((s, s, 3), _colour(rng, 200, 235), np.uint8)
    rng = rng if detail is None else detail
    img = _noise(rng, img, 8.0)
    k = 700
    ys, xs = rng.integers(0, s, k), rng.integers(0, s, k)
    img[ys, xs] = 110
    i, j = (int(v) for v in rng.integers(0, n, 2))
    img[i * t + 4 : (i + 1) * t - 4, j * t + 4 : (j + 1) * t - 4] = 252
    img[i * t + 4 : (i + 1) * t - 4, j * t + t // 2] = 200
    for a in range(n):
        img[a * t : a * t + 3, :] = 150
        img[:, a * t : a * t + 3] = 150
    return img


# Office walls (the thesis' office, docs/theory.md section 4): plain paint with few features. A paint
# texture is nearly uniform on purpose — real painted walls give local features almost nothing.
def _paint_colour(rng: np.random.Generator) -> np.ndarray:
    tints = ((236, 234, 226), (228, 230, 232), (240, 236, 222), (222, 226, 214), (234, 226, 220))
    return np.clip(np.array(tints[int(rng.integers(0, len(tints)))], np.float32) + rng.normal(0, 3, 3), 0, 255)


def _paint_base(rng: np.random.Generator) -> np.ndarray:
    """Painted wall: one colour with faint roller noise and a skirting board along the floor."""
    s = _PROC_PX
    img = np.empty((s, s, 3), np.float32)
    img[:] = _paint_colour(rng)
    img += cv2.GaussianBlur(rng.normal(0, 2.0, (s, s)).astype(np.float32), (0, 0), 3.0)[:, :, None]
    skirting = np.array(_colour(rng, 60, 140), np.float32)
    img[s - 10 :, :] = skirting  # 10 of 256 px: about 10 cm of a 2.5 m wall
    img[s - 11, :] = skirting * 0.6
    return img


def _paint(rng: np.random.Generator) -> np.ndarray:
    return np.clip(_paint_base(rng), 0, 255).astype(np.uint8)


def _fitting(rng: np.random.Generator) -> np.ndarray:
    """Paint with one or two small fittings: switch, socket, radiator, extinguisher sign, thermostat."""
    img = np.clip(_paint_base(rng), 0, 255).astype(np.uint8)
    s = _PROC_PX
    for _ in range(int(rng.integers(1, 3))):
        kind = int(rng.integers(0, 5))
        x = int(rng.integers(20, s - 60))
        if kind == 0:  # light switch at 1.1 m
            y = int(s * (1 - 1.1 / 2.5))
            cv2.rectangle(img, (x, y), (x + 9, y + 14), (245, 245, 240), -1)
            cv2.rectangle(img, (x, y), (x + 9, y + 14), (150, 150, 150), 1)
            cv2.rectangle(img, (x + 3, y + 4), (x + 6, y + 10), (200, 200, 200), -1)
        elif kind == 1:  # socket at 0.3 m
            y = int(s * (1 - 0.3 / 2.5))
            cv2.rectangle(img, (x, y), (x + 12, y + 10), (240, 240, 236), -1)
            cv2.rectangle(img, (x, y), (x + 12, y + 10), (140, 140, 140), 1)
            cv2.circle(img, (x + 4, y + 5), 1, (60, 60, 60), -1)
            cv2.circle(img, (x + 8, y + 5), 1, (60, 60, 60), -1)
        elif kind == 2:  # radiator under a window sill height
            w = int(rng.integers(50, 90))
            x = min(x, s - w - 2)
            y0, y1 = int(s * (1 - 0.75 / 2.5)), int(s * (1 - 0.15 / 2.5))
            cv2.rectangle(img, (x, y0), (x + w, y1), (235, 235, 232), -1)
            for xi in range(x + 3, x + w - 2, 5):
                cv2.line(img, (xi, y0 + 2), (xi, y1 - 2), (190, 190, 186), 1)
            cv2.rectangle(img, (x, y0), (x + w, y1), (160, 160, 156), 1)
        elif kind == 3:  # extinguisher sign: a red square with a white pictogram
            y = int(s * (1 - 1.8 / 2.5))
            cv2.rectangle(img, (x, y), (x + 18, y + 18), (200, 30, 30), -1)
            cv2.rectangle(img, (x + 6, y + 4), (x + 11, y + 15), (250, 250, 250), -1)
        else:  # thermostat / alarm panel
            y = int(s * (1 - 1.5 / 2.5))
            cv2.rectangle(img, (x, y), (x + 14, y + 18), (225, 225, 220), -1)
            cv2.rectangle(img, (x + 2, y + 3), (x + 11, y + 8), (70, 90, 80), -1)
            cv2.rectangle(img, (x, y), (x + 14, y + 18), (120, 120, 120), 1)
    return _noise(rng, img, 1.0)


def _door(rng: np.random.Generator) -> np.ndarray:
    """Paint with a door: frame, leaf, handle and a small sign."""
    img = np.clip(_paint_base(rng), 0, 255).astype(np.uint8)
    s = _PROC_PX
    dw = int(rng.integers(80, 100))  # a 0.9 m leaf on a 2.5 m wall is about 92 px of 256
    dx = int(rng.integers(20, s - dw - 20))
    top = int(s * (1 - 2.05 / 2.5))
    leaf = _colour(rng, 60, 200) if rng.random() < 0.5 else (205, 175, 130)
    cv2.rectangle(img, (dx - 5, top - 5), (dx + dw + 5, s - 1), _colour(rng, 90, 200), -1)  # frame
    cv2.rectangle(img, (dx, top), (dx + dw, s - 1), leaf, -1)
    hy = int(s * (1 - 1.05 / 2.5))
    hx = dx + dw - 12 if rng.random() < 0.5 else dx + 6
    cv2.rectangle(img, (hx, hy), (hx + 7, hy + 3), (200, 200, 195), -1)
    if rng.random() < 0.7:
        sy = int(s * (1 - 1.6 / 2.5))
        cv2.rectangle(img, (dx + 20, sy), (dx + dw - 20, sy + 12), (245, 245, 245), -1)
        _scribble(rng, img, dx + 20, sy - 8, dx + dw - 20, sy + 12, (30, 30, 30))
    return _noise(rng, img, 1.5)


def _frame(rng: np.random.Generator) -> np.ndarray:
    """Paint with one framed poster or notice at eye level (a sparse poster)."""
    img = np.clip(_paint_base(rng), 0, 255).astype(np.uint8)
    s = _PROC_PX
    w, h = int(rng.integers(50, 100)), int(rng.integers(50, 80))
    x = int(rng.integers(10, s - w - 10))
    y = int(s * (1 - 1.9 / 2.5))
    poster = _poster(rng)
    img[y : y + h, x : x + w] = cv2.resize(poster, (w, h), interpolation=cv2.INTER_AREA)
    cv2.rectangle(img, (x, y), (x + w, y + h), _colour(rng, 10, 70), 2)
    return img


#: Procedural texture kinds: name -> generator(rng) -> (256, 256, 3) uint8 RGB.
PROCEDURAL: dict[str, Callable[[np.random.Generator], np.ndarray]] = {
    "poster": _poster,
    "bricks": _bricks,
    "board": _board,
    "panels": _panels,
    "tiles": _tiles,
    "ceiling": _ceiling,
    "paint": _paint,
    "fitting": _fitting,
    "door": _door,
    "frame": _frame,
}


#: Kinds that take a second generator for the details of a variant (``texture_variant``).
_SURFACES = frozenset({"tiles", "ceiling"})

# Each kind's random stream; fixed so that adding a kind never changes the pixels of existing worlds.
_KIND_STREAM = {"board": 0, "bricks": 1, "ceiling": 2, "panels": 3, "poster": 4, "tiles": 5,
                "paint": 6, "fitting": 7, "door": 8, "frame": 9}


@functools.lru_cache(maxsize=128)
def _procedural(name: str, seed: int, variant: int = 0) -> np.ndarray:
    rng = np.random.default_rng([seed, _KIND_STREAM[name]])
    if variant == 0:
        img = PROCEDURAL[name](rng)
    else:  # another draw: of the details only for a floor or ceiling (same base colour), else of everything
        detail = np.random.default_rng([seed, _KIND_STREAM[name], variant])
        img = PROCEDURAL[name](rng, detail) if name in _SURFACES else PROCEDURAL[name](detail)
    img = np.ascontiguousarray(img, dtype=np.uint8)
    img.setflags(write=False)
    return img
