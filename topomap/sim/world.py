"""Indoor worlds: floor plans of corridors, junctions and rooms with textured walls, and named routes.

Floor-plan convention (docs/theory.md section 1, :mod:`topomap.motion`): points are ``(x, z)`` in metres
on the floor, drawn with x to the right and z upwards; heights are metres above the floor. Every
wall runs from the floor to the ceiling (``wall_height_m``); only its free side is drawn, which is
the *left* side of the segment ``(x0, z0) -> (x1, z1)``.

:func:`generate_world` lays out a seeded lattice of junctions joined by corridors (the lattice
perimeter is always kept, so the world has at least one loop; inner corridors are kept at random,
making T and X junctions and more loops), attaches rooms through doors, carves the result into an
occupancy grid and reads the walls back from the grid's boundary. Walls are split into panels that
each carry one texture (see :mod:`topomap.sim.textures`).

Routes are waypoint polylines along corridor centre lines: ``loop`` goes once around the perimeter
(counter-clockwise, back to its start), ``room1``, ``room2``, ... lead from the loop's start into each
room. A world is saved as a small JSON file (:meth:`World.save` / :func:`load_world`).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import networkx as nx
import numpy as np

from topomap.errors import DatasetError, unknown_choice
from topomap.sim import textures as tx

__all__ = [
    "Wall",
    "Rect",
    "Marker",
    "WaypointRoute",
    "World",
    "generate_world",
    "default_world",
    "load_world",
    "resolve_world",
    "WORLD_FORMAT",
    "WORLD_VERSION",
    "WALL_HEIGHT_M",
    "segment_distances",
    "WORLD_STYLES",
    "office_world",
]

WORLD_FORMAT = "topomap-world"
WORLD_VERSION = 2  # 2: tile_variants (a file of version 1 has none: one floor and ceiling texture tiled everywhere)
WALL_HEIGHT_M = 2.5
GRID_M = 0.25  # occupancy-grid cell of the generator [m]
WALL_THICKNESS_M = 0.5  # solid margin kept between two free spaces [m]
DOOR_WIDTH_M = 1.5
_MAX_TILE_M = 3.0  # floor/ceiling rectangles are cut to at most this side, for visibility culling [m]

#: Limits of a world file (the largest generated world, 6 x 6 junctions with 20 rooms, has 383 walls,
#: 225 free rectangles and a 30 KB file): a stranger's file beyond them is refused before it is built.
MAX_WORLD_BYTES = 16 << 20
MAX_WALLS = 5000
MAX_FREE_RECTS = 20_000
MAX_ROUTES = 100
MAX_WAYPOINTS = 10_000
MAX_MARKERS = 1000
MAX_TEXTURES = 1024  # distinct texture keys: each becomes an image in memory
MAX_EXTENT_M = 10_000.0  # |coordinate| bound [m]
MAX_WALL_HEIGHT_M = 100.0
MAX_FREE_AREA_M2 = 100_000.0  # the renderer cuts the free floor into cells of about a metre: bounded work
MAX_TILE_VARIANTS = 64
#: Floor and ceiling texture variants of a generated world (World.tile_variants).
TILE_VARIANTS = 16


@dataclass(frozen=True)
class Wall:
    """A wall panel from the floor to the ceiling over the segment ``(x0, z0) -> (x1, z1)`` [m].

    The drawn side faces the free space on the left of the segment; ``texture`` is a texture key.
    """

    x0: float
    z0: float
    x1: float
    z1: float
    texture: str

    @property
    def length(self) -> float:
        return math.hypot(self.x1 - self.x0, self.z1 - self.z0)


@dataclass(frozen=True)
class Rect:
    """An axis-aligned rectangle of free floor ``[x0, x1] x [z0, z1]`` [m] (``x0 < x1``, ``z0 < z1``)."""

    x0: float
    z0: float
    x1: float
    z1: float

    def contains(self, x: float, z: float) -> bool:
        return self.x0 <= x <= self.x1 and self.z0 <= z <= self.z1


@dataclass(frozen=True)
class Marker:
    """A small coloured ball at a known position (a docs/theory.md 'marker' landmark).

    ``x, z`` on the floor plan and ``height_m`` above the floor [m]; ``radius_m`` [m]; ``color`` RGB 0-255.
    """

    x: float
    z: float
    height_m: float
    radius_m: float = 0.03
    color: tuple[int, int, int] = (255, 0, 255)

    def __post_init__(self) -> None:
        object.__setattr__(self, "color", tuple(int(c) for c in self.color))


@dataclass(frozen=True)
class WaypointRoute:
    """A named polyline of ``(x, z)`` waypoints [m]; ``closed`` routes end where they start."""

    name: str
    waypoints: tuple[tuple[float, float], ...]
    closed: bool = False

    def __post_init__(self) -> None:
        pts = tuple((float(x), float(z)) for x, z in self.waypoints)
        object.__setattr__(self, "waypoints", pts)
        if len(pts) < 2:
            raise DatasetError(f"route {self.name!r} needs at least 2 waypoints, got {len(pts)}")

    @property
    def points(self) -> np.ndarray:
        """(N, 2) float64 waypoints."""
        return np.asarray(self.waypoints, dtype=float)

    @property
    def length_m(self) -> float:
        return float(np.linalg.norm(np.diff(self.points, axis=0), axis=1).sum())


@dataclass(frozen=True)
class World:
    """A floor plan with textured walls, floor and ceiling, markers and named routes.

    ``walls``: wall panels; ``free``: the free floor as disjoint rectangles (floor and ceiling are
    drawn over them); ``routes``: named waypoint polylines; ``markers``: small coloured balls;
    ``floor_texture`` / ``ceiling_texture``: texture keys tiled every ``textures.FLOOR_TILE_M`` /
    ``CEILING_TILE_M``; ``tile_variants``: each such tile shows one of this many variants of its texture
    (:func:`~topomap.sim.textures.texture_variant`), chosen by a hash of its position — a floor of one
    texture repeated every 2 m matches itself pixel for pixel at every place, and a camera seeing
    mostly floor then verifies a place 16 m away as well as its own (1: that periodic floor, as world
    files of version 1 have); ``texture_dir``: the user's photograph folder for ``user:`` textures (None:
    only shipped and procedural textures); ``seed``: the generator seed (None if hand-made).
    """

    walls: tuple[Wall, ...]
    free: tuple[Rect, ...]
    routes: tuple[WaypointRoute, ...] = ()
    markers: tuple[Marker, ...] = ()
    wall_height_m: float = WALL_HEIGHT_M
    floor_texture: str = "proc:tiles:0"
    ceiling_texture: str = "proc:ceiling:0"
    tile_variants: int = 1
    texture_dir: str | None = None
    seed: int | None = None
    name: str = "world"
    _segments: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        for name in ("walls", "free", "routes", "markers"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        if isinstance(self.tile_variants, bool) or not isinstance(self.tile_variants, int) or not (
                1 <= self.tile_variants <= MAX_TILE_VARIANTS):
            raise DatasetError(f"tile_variants {str(self.tile_variants)[:30]} must be a whole number from 1 to {MAX_TILE_VARIANTS}")
        if not (math.isfinite(self.wall_height_m) and self.wall_height_m > 0):
            raise DatasetError(f"wall height {self.wall_height_m} must be a positive number of metres")
        if not self.walls:
            raise DatasetError(f"world {self.name!r} has no walls")
        if not self.free:
            raise DatasetError(f"world {self.name!r} has no free floor")
        names = [r.name for r in self.routes]
        if len(set(names)) != len(names):
            raise DatasetError(f"world {self.name!r} has two routes with the same name")
        seg = np.array([[w.x0, w.z0, w.x1, w.z1] for w in self.walls], dtype=float)
        if not np.isfinite(seg).all() or (np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1]) <= 0).any():
            raise DatasetError(f"world {self.name!r} has a wall with non-finite or coincident end points")
        seg.setflags(write=False)
        object.__setattr__(self, "_segments", seg)

    # ------------------------------------------------------------------ queries
    @property
    def segments(self) -> np.ndarray:
        """(S, 4) float64 wall segments ``x0, z0, x1, z1`` [m] (read-only)."""
        return self._segments

    @property
    def route_names(self) -> list[str]:
        return [r.name for r in self.routes]

    def route(self, name: str) -> WaypointRoute:
        """The route called ``name``; an unknown name lists the valid ones."""
        for r in self.routes:
            if r.name == name:
                return r
        raise unknown_choice("route", name, self.route_names or ["(this world has no routes)"])

    def bounds(self) -> tuple[float, float, float, float]:
        """``(xmin, zmin, xmax, zmax)`` of the walls [m]."""
        s = self._segments
        return (float(min(s[:, 0].min(), s[:, 2].min())), float(min(s[:, 1].min(), s[:, 3].min())),
                float(max(s[:, 0].max(), s[:, 2].max())), float(max(s[:, 1].max(), s[:, 3].max())))

    def is_free(self, x: float, z: float) -> bool:
        """Whether the floor point ``(x, z)`` lies in free space."""
        return any(r.contains(x, z) for r in self.free)

    def clearance(self, x: float, z: float) -> float:
        """Distance [m] from the floor point ``(x, z)`` to the nearest wall."""
        return float(segment_distances(np.array([[x, z]]), self._segments).min())

    # ------------------------------------------------------------------ files
    def to_dict(self) -> dict:
        return {
            "format": WORLD_FORMAT,
            "version": WORLD_VERSION,
            "name": self.name,
            "seed": self.seed,
            "wall_height_m": self.wall_height_m,
            "floor_texture": self.floor_texture,
            "ceiling_texture": self.ceiling_texture,
            "tile_variants": self.tile_variants,
            "texture_dir": self.texture_dir,
            "walls": [[_r(w.x0), _r(w.z0), _r(w.x1), _r(w.z1), w.texture] for w in self.walls],
            "free": [[_r(f.x0), _r(f.z0), _r(f.x1), _r(f.z1)] for f in self.free],
            "routes": {r.name: {"closed": r.closed, "waypoints": [[_r(x), _r(z)] for x, z in r.waypoints]} for r in self.routes},
            "markers": [
                {"x": m.x, "z": m.z, "height_m": m.height_m, "radius_m": m.radius_m, "color": list(m.color)}
                for m in self.markers
            ],
        }

    @classmethod
    def from_dict(cls, d: dict, source: str = "world") -> World:
        """Inverse of :meth:`to_dict`; anything malformed raises :class:`DatasetError`."""
        if not isinstance(d, dict) or d.get("format") != WORLD_FORMAT:
            raise DatasetError(f"{source} is not a topomap world file (no \"format\": \"{WORLD_FORMAT}\")")
        version = d.get("version")
        if not isinstance(version, int) or version < 1:
            raise DatasetError(f"{source} has no valid world format version")
        if version > WORLD_VERSION:
            raise DatasetError(f"{source} was written by a newer topomap (world format {version}); upgrade topomap")
        try:
            _check_limits(d)
            return cls(
                walls=tuple(Wall(float(a), float(b), float(c), float(e), str(t)) for a, b, c, e, t in d["walls"]),
                free=tuple(Rect(*(float(v) for v in f)) for f in d["free"]),
                routes=tuple(
                    WaypointRoute(str(name), tuple((float(x), float(z)) for x, z in r["waypoints"]), bool(r.get("closed", False)))
                    for name, r in d.get("routes", {}).items()
                ),
                markers=tuple(
                    Marker(float(m["x"]), float(m["z"]), float(m["height_m"]), float(m.get("radius_m", 0.03)),
                           tuple(m.get("color", (255, 0, 255))))
                    for m in d.get("markers", [])
                ),
                wall_height_m=float(d.get("wall_height_m", WALL_HEIGHT_M)),
                floor_texture=str(d.get("floor_texture", "proc:tiles:0")),
                ceiling_texture=str(d.get("ceiling_texture", "proc:ceiling:0")),
                tile_variants=d.get("tile_variants", 1),
                texture_dir=None if d.get("texture_dir") is None else str(d["texture_dir"]),
                seed=None if d.get("seed") is None else int(d["seed"]),
                name=str(d.get("name", "world")),
            )
        except DatasetError as e:
            raise DatasetError(f"{source} is corrupt: {e}") from None
        except (KeyError, TypeError, ValueError, AttributeError) as e:
            what = f"missing field {e.args[0]!r}" if isinstance(e, KeyError) else str(e)
            raise DatasetError(f"{source} is corrupt ({what}); regenerate it with 'topomap sim make-world'") from None

    def save(self, path: str | Path) -> Path:
        """Write the world as JSON; :func:`load_world` reads it back."""
        path = Path(path)
        path.write_text(json.dumps(self.to_dict(), separators=(",", ":")) + "\n")
        return path

    def retextured(self, texture_dir: str | Path | None, seed: int | None = None) -> World:
        """The same floor plan with wall photographs drawn from ``texture_dir`` (None: the shipped set)."""
        base = (self.seed or 0) if seed is None else seed
        rng = np.random.default_rng([int(base), 7])
        pool = _texture_pool(rng, texture_dir)
        walls = _assign_textures(rng, [(w.x0, w.z0, w.x1, w.z1) for w in self.walls], pool)
        tdir = None if texture_dir is None else str(Path(texture_dir).resolve())
        return replace(self, walls=tuple(walls), texture_dir=tdir)


def _r(v: float) -> float:
    return round(float(v), 6)


def _check_limits(d: dict) -> None:
    """Counts, ranges and texture keys of a world dict, before anything is built from it (a file
    from elsewhere may hold a million walls, 1e300 m coordinates or a texture path out of its folder)."""
    def seq(name, limit):
        v = d.get(name, [] if name != "routes" else {})
        if not isinstance(v, (list, dict)):
            raise DatasetError(f"{name!r} must be a list")
        if len(v) > limit:
            raise DatasetError(f"it has {len(v)} {name}, more than the {limit} topomap builds")
        return v

    walls = seq("walls", MAX_WALLS)
    free = seq("free", MAX_FREE_RECTS)
    routes = seq("routes", MAX_ROUTES)
    markers = seq("markers", MAX_MARKERS)
    if not isinstance(routes, dict):
        raise DatasetError("'routes' must map route names to waypoint lists")

    def finite(v, what, lo=-MAX_EXTENT_M, hi=MAX_EXTENT_M):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and lo <= v <= hi):
            raise DatasetError(f"{what} {str(v)[:30]} is not a number between {lo:g} and {hi:g}")

    for w in walls:
        if not isinstance(w, list) or len(w) != 5:
            raise DatasetError("a wall must be [x0, z0, x1, z1, texture]")
        for v in w[:4]:
            finite(v, "wall coordinate")
    area = 0.0
    for f in free:
        if not isinstance(f, list) or len(f) != 4:
            raise DatasetError("a free rectangle must be [x0, z0, x1, z1]")
        for v in f:
            finite(v, "free-floor coordinate")
        area += abs((f[2] - f[0]) * (f[3] - f[1]))
    if area > MAX_FREE_AREA_M2:
        raise DatasetError(f"its free floor covers {area:.0f} m2, more than the {MAX_FREE_AREA_M2:.0f} m2 topomap renders")
    for name, r in routes.items():
        pts = r.get("waypoints") if isinstance(r, dict) else None
        if not isinstance(pts, list) or len(pts) > MAX_WAYPOINTS:
            raise DatasetError(f"route {str(name)[:40]!r} must hold at most {MAX_WAYPOINTS} waypoints")
        for pt in pts:
            if not isinstance(pt, list) or len(pt) != 2:
                raise DatasetError(f"route {str(name)[:40]!r} has a waypoint that is not [x, z]")
            for v in pt:
                finite(v, "waypoint coordinate")
    for mk in markers:
        if not isinstance(mk, dict):
            raise DatasetError("a marker must be an object with x, z, height_m")
        for k in ("x", "z"):
            finite(mk.get(k), f"marker {k}")
        finite(mk.get("height_m"), "marker height_m", 0.0, MAX_WALL_HEIGHT_M)
        finite(mk.get("radius_m", 0.03), "marker radius_m", 1e-4, 10.0)
        colour = mk.get("color", [255, 0, 255])
        if not isinstance(colour, list) or len(colour) != 3:
            raise DatasetError("a marker colour must be [r, g, b]")
        for c in colour:
            finite(c, "marker colour channel", 0, 255)
    finite(d.get("wall_height_m", WALL_HEIGHT_M), "wall height", 0.1, MAX_WALL_HEIGHT_M)
    if d.get("seed") is not None and (isinstance(d["seed"], bool) or not isinstance(d["seed"], int) or d["seed"] < 0):
        raise DatasetError("the world seed must be a non-negative integer")
    if len(str(d.get("name", ""))) > 200:
        raise DatasetError("the world name is longer than 200 characters")
    keys = {d.get("floor_texture", "proc:tiles:0"), d.get("ceiling_texture", "proc:ceiling:0")}
    keys |= {w[4] for w in walls}
    if len(keys) > MAX_TEXTURES:
        raise DatasetError(f"it uses {len(keys)} distinct textures, more than the {MAX_TEXTURES} topomap loads")
    for k in keys:
        tx.check_texture_key(k)


def load_world(path: str | Path) -> World:
    """Read a world saved by :meth:`World.save`."""
    path = Path(path)
    if not path.exists():
        raise DatasetError(f"world file {path} does not exist; create one with 'topomap sim make-world' or give a seed")
    if not path.is_file():
        kind = "a folder" if path.is_dir() else "not a regular file (a FIFO or a device?)"
        raise DatasetError(f"world {path} is {kind}; give a world JSON file (topomap sim make-world) or a seed")
    from topomap.images import read_file_bytes

    data = read_file_bytes(path, max_bytes=MAX_WORLD_BYTES, what="world file")
    try:
        parsed = json.loads(data.decode("utf-8"))
    except UnicodeDecodeError as e:
        raise DatasetError(f"cannot read world file {path}: {e}") from None
    except json.JSONDecodeError as e:
        raise DatasetError(f"world file {path} is not valid JSON ({e.msg} at line {e.lineno}); regenerate it") from None
    except RecursionError:
        raise DatasetError(f"world file {path} nests its JSON too deeply; regenerate it") from None
    return World.from_dict(parsed, source=f"world file {path}")


def resolve_world(spec: str | int | Path | World | None, textures: str | Path | None = None) -> World:
    """A world from a CLI-style spec: None/``default``, a seed (``"7"``), a style with an optional
    seed (``"office"``, ``"office:7"``, :data:`WORLD_STYLES`) or a world JSON file.

    ``textures`` (a folder of photographs) replaces the wall photographs.
    """
    if isinstance(spec, World):
        world = spec
        return world if textures is None else world.retextured(textures)
    if spec is None or str(spec) == "default":
        return default_world(textures=textures)
    s = str(spec)
    if (preset := _preset_world(s, textures)) is not None:
        return preset
    if isinstance(spec, int) or s.lstrip("-").isdigit():
        if int(s) < 0 or int(s) >= 2**63:
            raise DatasetError(f"world seed {s} must be an integer from 0 to 2**63 - 1")
        return generate_world(int(s), textures=textures)
    path = Path(s)
    if not path.exists():
        raise DatasetError(f"world {s!r} is neither a seed (an integer), 'default' nor an existing world file")
    world = load_world(path)
    return world if textures is None else world.retextured(textures)


# ---------------------------------------------------------------------- geometry
def segment_distances(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Euclidean distances (N, S) from points (N, 2) to segments (S, 4) ``x0, z0, x1, z1``."""
    p = np.asarray(points, dtype=float).reshape(-1, 1, 2)
    a = segments[None, :, 0:2]
    d = segments[None, :, 2:4] - a
    dd = (d * d).sum(-1)
    t = np.clip(((p - a) * d).sum(-1) / np.where(dd > 0, dd, 1.0), 0.0, 1.0)
    q = a + t[..., None] * d
    return np.sqrt(((p - q) ** 2).sum(-1))


# ---------------------------------------------------------------------- generator
def default_world(textures: str | Path | None = None) -> World:
    """The reference world of tests and benchmarks: ``generate_world(0)`` (3 x 3 junctions, 4 rooms)."""
    world = generate_world(0, textures=textures)
    return replace(world, name="default")


def generate_world(
    seed: int = 0,
    *,
    lattice: tuple[int, int] = (3, 3),
    spacing_m: tuple[float, float] = (6.0, 8.5),
    rooms: int = 4,
    inner_corridor_prob: float = 0.5,
    wall_height_m: float = WALL_HEIGHT_M,
    textures: str | Path | None = None,
    name: str | None = None,
    style: str = "default",
) -> World:
    """A seeded floor plan: ``lattice`` junctions ``spacing_m`` apart joined by corridors, plus rooms.

    ``lattice``: junctions along x and z (2..6 each); ``spacing_m``: range of junction spacing [m];
    ``rooms``: rooms to attach (fewer if they do not fit); ``inner_corridor_prob``: chance of keeping
    each corridor off the perimeter; ``textures``: a folder of photographs for the walls;
    ``style``: how walls are dressed (:data:`WORLD_STYLES`: ``default`` half photographs, ``office``
    plain paint with sparse posters, doors and fittings).
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= int(seed) < 2**63:
        raise DatasetError(f"world seed {seed!r} must be an integer from 0 to 2**63 - 1")
    if style not in WORLD_STYLES:
        raise unknown_choice("world style", style, WORLD_STYLES)
    nx_, nz_ = (int(v) for v in lattice)
    if not (2 <= nx_ <= 6 and 2 <= nz_ <= 6):
        raise DatasetError(f"lattice {lattice} must have 2 to 6 junctions along each axis")
    lo, hi = (float(v) for v in spacing_m)
    if not (5.0 <= lo <= hi <= 30.0):
        raise DatasetError(f"spacing_m {spacing_m} must satisfy 5 <= min <= max <= 30 metres")
    if rooms < 0:
        raise DatasetError(f"rooms={rooms} must not be negative")
    if not 0.0 <= inner_corridor_prob <= 1.0:
        raise DatasetError(f"inner_corridor_prob={inner_corridor_prob} must lie in [0, 1]")
    rng = np.random.default_rng([int(seed), 0])

    def snap(v: float) -> float:
        return round(v / GRID_M) * GRID_M

    margin = 8.0  # room for rooms outside the perimeter [m]
    xs = margin + np.concatenate([[0.0], np.cumsum([snap(rng.uniform(lo, hi)) for _ in range(nx_ - 1)])])
    zs = margin + np.concatenate([[0.0], np.cumsum([snap(rng.uniform(lo, hi)) for _ in range(nz_ - 1)])])
    pos = {(i, j): (float(xs[i]), float(zs[j])) for i in range(nx_) for j in range(nz_)}

    # Corridors: the perimeter always (the loop), inner ones at random; every junction connected.
    def perimeter(e):
        (i0, j0), (i1, j1) = e
        return (j0 == j1 and j0 in (0, nz_ - 1)) or (i0 == i1 and i0 in (0, nx_ - 1))

    lattice_edges = [((i, j), (i + 1, j)) for j in range(nz_) for i in range(nx_ - 1)]
    lattice_edges += [((i, j), (i, j + 1)) for i in range(nx_) for j in range(nz_ - 1)]
    keep = [e for e in lattice_edges if perimeter(e) or rng.random() < inner_corridor_prob]
    g = nx.Graph(keep)
    inner = [e for e in lattice_edges if not perimeter(e)]
    for e in inner:  # no isolated junction
        if e[0] not in g or e[1] not in g:
            g.add_edge(*e)
    if inner and all(perimeter(e) for e in g.edges):  # at least one inner corridor: junctions, loops
        g.add_edge(*inner[int(rng.integers(0, len(inner)))])
    edges = sorted(tuple(sorted(e)) for e in g.edges)  # (low, high) junction pairs
    half_width = {e: float(rng.choice([0.75, 1.0, 1.0, 1.25])) for e in edges}

    size_x = xs[-1] + margin
    size_z = zs[-1] + margin
    free = np.zeros((int(round(size_x / GRID_M)), int(round(size_z / GRID_M))), dtype=bool)

    def idx(v: float) -> int:
        return int(round(v / GRID_M))

    def carve(x0, z0, x1, z1):
        free[idx(x0) : idx(x1), idx(z0) : idx(z1)] = True

    def occupied(x0, z0, x1, z1) -> bool:
        return bool(free[max(0, idx(x0)) : idx(x1), max(0, idx(z0)) : idx(z1)].any())

    junction_half = {n: max(hw for e, hw in half_width.items() if n in e) for n in g.nodes}
    for e in edges:
        (xa, za), (xb, zb) = pos[e[0]], pos[e[1]]
        hw = half_width[e]
        carve(xa - hw, za - hw, xb + hw, zb + hw)
    for n, h in junction_half.items():
        x, z = pos[n]
        carve(x - h, z - h, x + h, z + h)

    # Rooms beside corridors, each joined to its corridor by a door.
    room_list = []  # (rect, door on the corridor centre line, a point 1 m inside the door, corridor)
    candidates = [(e, s) for e in edges for s in (-1, 1)]
    order = rng.permutation(len(candidates))
    for k in order:
        if len(room_list) >= rooms:
            break
        e, side = candidates[int(k)]
        (xa, za), (xb, zb) = pos[e[0]], pos[e[1]]
        horizontal = za == zb
        hw = half_width[e]
        a0, a1 = (xa, xb) if horizontal else (za, zb)  # extent along the corridor
        c = za if horizontal else xa  # centre line coordinate across the corridor
        a0 += junction_half[e[0]] + 0.5
        a1 -= junction_half[e[1]] + 0.5
        width = snap(rng.uniform(3.0, 5.5))
        depth = snap(rng.uniform(3.0, 4.5))
        if a1 - a0 < width:
            width = snap(a1 - a0 - GRID_M)
        if width < 2.5:
            continue
        start = snap(rng.uniform(a0, a1 - width))
        near = c + side * (hw + WALL_THICKNESS_M)
        far = near + side * depth
        b0, b1 = min(near, far), max(near, far)
        rect = (start, b0, start + width, b1) if horizontal else (b0, start, b1, start + width)
        t = WALL_THICKNESS_M
        if occupied(rect[0] - t, rect[1] - t, rect[2] + t, rect[3] + t):
            continue
        door_a = snap(rng.uniform(start + 0.25, start + width - 0.25 - DOOR_WIDTH_M))
        d0, d1 = min(c + side * hw, near), max(c + side * hw, near)
        door = (door_a, d0, door_a + DOOR_WIDTH_M, d1) if horizontal else (d0, door_a, d1, door_a + DOOR_WIDTH_M)
        carve(*rect)
        carve(*door)
        mid = door_a + DOOR_WIDTH_M / 2
        on_line = (mid, c) if horizontal else (c, mid)
        inside_c = near + side * min(1.0, depth / 2)
        inside = (mid, inside_c) if horizontal else (inside_c, mid)
        room_list.append((rect, on_line, inside, e))

    walls_geom = _walls_from_grid(free, rng)
    pool = _texture_pool(rng, textures)
    walls = _assign_textures(rng, walls_geom, pool, style)
    floor = f"proc:tiles:{int(rng.integers(0, 1000))}"
    ceiling = f"proc:ceiling:{int(rng.integers(0, 1000))}"
    free_rects = tuple(_rects_from_grid(free))

    # Routes.
    perim = [(i, 0) for i in range(nx_)] + [(nx_ - 1, j) for j in range(1, nz_)]
    perim += [(i, nz_ - 1) for i in range(nx_ - 2, -1, -1)] + [(0, j) for j in range(nz_ - 2, 0, -1)]
    start = ((xs[0] + xs[1]) / 2, float(zs[0]))
    loop_pts = [start] + [pos[n] for n in perim[1:]] + [pos[perim[0]], start]
    routes = [WaypointRoute("loop", tuple(loop_pts), closed=True)]
    dist = dict(nx.all_pairs_dijkstra_path_length(g, weight=lambda a, b, _: _dist(pos[a], pos[b])))
    paths = dict(nx.all_pairs_dijkstra_path(g, weight=lambda a, b, _: _dist(pos[a], pos[b])))
    s_edge = ((0, 0), (1, 0))
    for r_i, (rect, on_line, inside, e) in enumerate(room_list, start=1):
        centre = ((rect[0] + rect[2]) / 2, (rect[1] + rect[3]) / 2)
        best = None
        if e == s_edge:
            best = (_dist(start, on_line), [])
        for a in s_edge:
            for b in e:
                cost = _dist(start, pos[a]) + dist[a][b] + _dist(pos[b], on_line)
                if best is None or cost < best[0] - 1e-9:
                    best = (cost, paths[a][b])
        pts = [start] + [pos[n] for n in best[1]] + [on_line, inside, centre]
        routes.append(WaypointRoute(f"room{r_i}", tuple(_dedupe(pts))))

    return World(
        walls=tuple(walls),
        free=free_rects,
        routes=tuple(routes),
        wall_height_m=float(wall_height_m),
        floor_texture=floor,
        ceiling_texture=ceiling,
        tile_variants=TILE_VARIANTS,
        texture_dir=None if textures is None else str(Path(textures).resolve()),
        seed=int(seed),
        name=name or (f"seed{int(seed)}" if style == "default" else f"{style}{int(seed)}"),
    )


def _dist(a, b) -> float:
    return math.hypot(a[0] - b[0], a[1] - b[1])


def _dedupe(pts):
    out = []
    for p in pts:
        if not out or _dist(out[-1], p) > 1e-6:
            out.append((float(p[0]), float(p[1])))
    return out


def _runs(mask: np.ndarray):
    """(start, stop) index pairs of the True runs of a 1-D boolean array."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1))


def _walls_from_grid(free: np.ndarray, rng: np.random.Generator) -> list[tuple[float, float, float, float]]:
    """Wall panels (x0, z0, x1, z1) along the free/solid boundary, free space on the left."""
    f = np.pad(free, 1)
    c = f[1:-1, 1:-1]
    g = GRID_M
    segs = []
    # boundary facing +x (solid at i-1): direction -z; facing -x (solid at i+1): +z
    for i in range(free.shape[0]):
        for j0, j1 in _runs(c[i] & ~f[i, 1:-1]):
            segs.append((i * g, j1 * g, i * g, j0 * g))
        for j0, j1 in _runs(c[i] & ~f[i + 2, 1:-1]):
            segs.append(((i + 1) * g, j0 * g, (i + 1) * g, j1 * g))
    # boundary facing +z (solid at j-1): direction +x; facing -z (solid at j+1): -x
    for j in range(free.shape[1]):
        for i0, i1 in _runs(c[:, j] & ~f[1:-1, j]):
            segs.append((i0 * g, j * g, i1 * g, j * g))
        for i0, i1 in _runs(c[:, j] & ~f[1:-1, j + 2]):
            segs.append((i1 * g, (j + 1) * g, i0 * g, (j + 1) * g))
    panels = []
    for x0, z0, x1, z1 in segs:
        length = math.hypot(x1 - x0, z1 - z0)
        cuts = [0.0]
        while length - cuts[-1] > 4.0:
            cuts.append(cuts[-1] + float(rng.uniform(1.5, 3.0)))
        cuts.append(length)
        for a, b in zip(cuts[:-1], cuts[1:]):
            ta, tb = a / length, b / length
            panels.append((x0 + ta * (x1 - x0), z0 + ta * (z1 - z0), x0 + tb * (x1 - x0), z0 + tb * (z1 - z0)))
    return panels


def _rects_from_grid(free: np.ndarray) -> list[Rect]:
    """Greedy decomposition of the free cells into disjoint rectangles of at most ``_MAX_TILE_M``."""
    todo = free.copy()
    g = GRID_M
    m = int(round(_MAX_TILE_M / g))
    rects = []
    for j in range(free.shape[1]):
        for i in range(free.shape[0]):
            if not todo[i, j]:
                continue
            i1 = i
            while i1 < free.shape[0] and todo[i1, j] and i1 - i < m:
                i1 += 1
            j1 = j + 1
            while j1 < free.shape[1] and j1 - j < m and todo[i:i1, j1].all():
                j1 += 1
            todo[i:i1, j:j1] = False
            rects.append(Rect(i * g, j * g, i1 * g, j1 * g))
    return rects


#: Procedural wall patterns and their weights.
_WALL_KINDS = ("poster", "poster", "poster", "board", "board", "bricks", "panels", "panels")
PHOTO_SHARE = 0.5  # chance that a wall panel shows a photograph, while unused ones remain


def _texture_pool(rng: np.random.Generator, texture_dir: str | Path | None) -> list[str]:
    """Photograph keys the walls draw from (each photograph plain and mirrored), in random order."""
    photos = tx.photo_keys(texture_dir)
    pool = photos + [f"{k}:flip" for k in photos]
    return [pool[i] for i in rng.permutation(len(pool))]


def _assign_textures(rng: np.random.Generator, panels, pool: list[str], style: str = "default") -> list[Wall]:
    """One texture per panel: about half photographs, each used once (identical walls in two places
    would make false loop closures certain), the others procedural patterns with their own seeds
    (the share and the patterns are the ``style``'s, :data:`WORLD_STYLES`)."""
    share, kinds = WORLD_STYLES[style]
    walls = []
    k = 0
    for x0, z0, x1, z1 in panels:
        if rng.random() < share and k < len(pool):
            key = pool[k]
            k += 1
        else:
            key = f"proc:{kinds[int(rng.integers(0, len(kinds)))]}:{int(rng.integers(0, 1_000_000))}"
        walls.append(Wall(_r(x0), _r(z0), _r(x1), _r(z1), key))  # rounded as in the JSON file
    return walls


# ---------------------------------------------------------------------- styles and presets
#: Wall styles: name -> (share of panels showing a photograph, procedural kinds drawn with repeats
#: as weights). ``office``: the thesis' office (docs/theory.md section 4), mostly plain paint; about one
#: panel in ten carries a poster, one in eight a door, one in five a small fitting.
WORLD_STYLES: dict[str, tuple[float, tuple[str, ...]]] = {
    "default": (PHOTO_SHARE, _WALL_KINDS),
    "office": (0.0, ("paint",) * 23 + ("fitting",) * 8 + ("door",) * 5 + ("frame",) * 4),
}


def office_world(seed: int = 0, **options) -> World:
    """A plain office: :func:`generate_world` with ``style="office"`` (same floor plans as the seed)."""
    return generate_world(seed, style="office", **options)


def _preset_world(spec: str, textures: str | Path | None) -> World | None:
    """``STYLE`` or ``STYLE:SEED`` (e.g. ``office:7``) for a non-default style; None otherwise."""
    style, _, seed = spec.partition(":")
    if style not in WORLD_STYLES or style == "default":
        return None
    if seed and not seed.lstrip("-").isdigit():
        raise DatasetError(f"world {spec!r}: the seed after '{style}:' must be an integer, like {style}:7")
    return generate_world(int(seed or 0), style=style, textures=textures)
