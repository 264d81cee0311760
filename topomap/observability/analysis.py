"""The rank test: exact generic rank of the observability codistribution, unobservable directions,
and the thesis' table (docs/theory.md section 2).

Method. The rows ``d L^j h`` of the codistribution (Hermann-Krener; with known inputs, the span of
all iterated Lie derivatives along the input fields) are evaluated exactly in GF(p) at a random point
by :mod:`topomap.observability.jets`. Every minor of the codistribution is a rational function with
integer coefficients, so its rank mod p at any point is a lower bound of the generic rank, and equals
it unless the point hits the zero set of a nonzero minor (probability ``<= degree / p``, with
``p ~ 2**30``). A second independent point with a second prime confirms it; the report keeps the
larger of the two ranks and says whether they agreed.

Unobservable directions: candidate symmetry fields of the system (rotation about a landmark,
translation, scaling) are evaluated at the same point and kept when they lie in the kernel (an exact
test, repeated at the second point); directions that change only the unknown inputs come from the
kernel restricted to the disturbance coordinates; whatever remains is reported by its support.
"""

from __future__ import annotations

import json
import logging
import os
import random
import time
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import sympy as sp
from sympy import GF
from sympy.polys.matrices import DomainMatrix

from topomap.errors import ConfigError, unknown_choice
from topomap.motion import VehicleKind, vehicle_kind
from topomap.observability import jets
from topomap.observability.system import DirectionKind, System, vehicle_landmark_system

__all__ = [
    "PRIMES",
    "Direction",
    "ObservabilityReport",
    "analyze",
    "codistribution_rows",
    "float_rank",
    "symbolic_rank",
    "TABLE_CONFIGURATIONS",
    "TableRow",
    "observability_table",
    "default_cache_dir",
]

log = logging.getLogger(__name__)

#: The two primes (< 2**30) of the two evaluation points.
PRIMES = (1073741789, 1073741783)
#: Bumped whenever a change could alter cached table cells.
ALGORITHM_VERSION = 1


# ----------------------------------------------------------------------------- results
@dataclass(frozen=True)
class Direction:
    """One unobservable direction at the evaluation point.

    ``field``: ``(state, sympy component)`` pairs of the vector field when the direction is a known
    symmetry (empty otherwise); ``support``: the states it changes.
    """

    kind: DirectionKind
    reading: str
    support: tuple[str, ...]
    field: tuple[tuple[str, sp.Expr], ...] = ()

    def to_dict(self) -> dict:
        return {
            "kind": self.kind.value,
            "reading": self.reading,
            "support": list(self.support),
            "field": {k: str(v) for k, v in self.field} if self.field else None,
        }


@dataclass(frozen=True)
class ObservabilityReport:
    """Result of :func:`analyze`.

    ``rank`` is the generic rank of the observability codistribution (exact, see module doc);
    ``ranks`` the ranks found at the two points; ``derivative_order`` the highest output derivative
    that raised the rank.
    """

    name: str
    state_names: tuple[str, ...]
    rank: int
    ranks: tuple[int, int]
    derivative_order: int
    directions: tuple[Direction, ...]
    seconds: float
    meta: dict = field(default_factory=dict, compare=False)

    @property
    def state_dimension(self) -> int:
        return len(self.state_names)

    @property
    def unobservable_dimension(self) -> int:
        return self.state_dimension - self.rank

    @property
    def confirmed(self) -> bool:
        return self.ranks[0] == self.ranks[1]

    @property
    def observable(self) -> bool:
        return self.unobservable_dimension == 0

    def to_dict(self) -> dict:
        return {
            "system": self.name,
            **self.meta,
            "states": list(self.state_names),
            "state_dimension": self.state_dimension,
            "rank": self.rank,
            "unobservable_dimension": self.unobservable_dimension,
            "directions": [d.to_dict() for d in self.directions],
            "confirmed": self.confirmed,
            "ranks_at_points": list(self.ranks),
            "primes": list(PRIMES),
            "derivative_order": self.derivative_order,
            "method": "exact rank over GF(p) at two random points",
            "seconds": round(self.seconds, 3),
        }


# ----------------------------------------------------------------------------- linear algebra mod p
def _dm(rows, p: int) -> DomainMatrix:
    rows = np.asarray(rows, dtype=np.int64)
    K = GF(p)
    return DomainMatrix.from_list([[int(v) for v in r] for r in rows], K) if rows.size else None


def rank_mod_p(rows, p: int) -> int:
    """Rank of an integer matrix over GF(p) (sympy DomainMatrix)."""
    rows = np.asarray(rows, dtype=np.int64)
    if rows.size == 0:
        return 0
    return int(_dm(rows % p, p).rank())


def nullspace_mod_p(rows, p: int, ncols: int) -> list[np.ndarray]:
    """A basis of the right kernel over GF(p), as int64 vectors in [0, p)."""
    rows = np.asarray(rows, dtype=np.int64).reshape(-1, ncols)
    if rows.shape[0] == 0:
        return [np.eye(ncols, dtype=np.int64)[i] for i in range(ncols)]
    ns = _dm(rows % p, p).nullspace().to_list()
    return [np.array([int(v) % p for v in vec], dtype=np.int64) for vec in ns]


def _in_kernel(M: np.ndarray, v: np.ndarray, p: int) -> bool:
    return bool(np.all(((M % p) * (v % p)[None, :] % p).sum(axis=1) % p == 0))


# ----------------------------------------------------------------------------- codistribution
def _program(system: System) -> tuple[jets.Program, tuple]:
    u = tuple(sp.Symbol(f"_u{j}") for j in range(len(system.known_fields)))
    drift = [
        system.drift[r] + sum((g[r] * u[j] for j, g in enumerate(system.known_fields)), sp.Integer(0))
        for r in range(system.dimension)
    ]
    if system.unknown_fields:
        raise ConfigError(f"system {system.name!r} still has unknown input fields; augment() it first")
    roots = {"drift": drift, "outputs": list(system.outputs)}
    for i, sym in enumerate(system.symmetries):
        roots[f"sym{i}"] = list(sym.field)
    prog = jets.compile_program(system.states, system.params, u, system.angles, roots)
    return prog, u


def _orders(system: System) -> tuple[int, int]:
    """(highest derivative order J, number of input samples S) that make the rows span the codistribution."""
    n = system.dimension
    if system.known_fields:
        # a word of length L in the input fields is isolated in y^(L (L + 1) / 2); L <= n - 1 suffices
        J = n * (n - 1) // 2 + 1
        S = n
    else:
        J = n  # the filtration d h, d L_f h, ... stops growing by order n - 1
        S = 1
    if system.max_derivative is not None:
        J = min(J, system.max_derivative) if system.known_fields else system.max_derivative
    return J, S


def codistribution_rows(system: System, field, seed: int):
    """Rows of the codistribution at a random point: ``(rows (J + 1, p * S, n), point, program)``."""
    prog, _ = _program(system)
    J, S = _orders(system)
    rng = np.random.default_rng(seed)
    for _attempt in range(5):
        point = jets.sample_point(prog, field, rng, S, J)
        try:
            rows, _ = jets.lie_rows(prog, field, point, J)
            break
        except ZeroDivisionError:  # the point hit a pole (probability ~ 1/p): draw another
            continue
    else:  # pragma: no cover
        raise ConfigError(f"system {system.name!r}: every sampled point hits a pole of the outputs")
    n = system.dimension
    return rows.reshape(J + 1, -1, n), point, prog


def _rank_by_order(rows: np.ndarray, p: int) -> tuple[int, int]:
    """(rank of all rows, lowest derivative order reaching it)."""
    J1, _, n = rows.shape
    full = rank_mod_p(rows.reshape(-1, n), p)
    lo, hi = 0, J1 - 1
    while lo < hi:  # ranks grow with the order: bisect for the first order with the full rank
        mid = (lo + hi) // 2
        if rank_mod_p(rows[: mid + 1].reshape(-1, n), p) == full:
            hi = mid
        else:
            lo = mid + 1
    return full, lo


def analyze(system: System, *, seed: int = 0, directions: bool = True) -> ObservabilityReport:
    """Generic rank of the observability codistribution of ``system``, exactly, at two random points.

    ``directions=False`` skips the reading of the unobservable directions (faster, for tables).
    """
    t0 = time.perf_counter()
    n = system.dimension
    results = []
    for i, p in enumerate(PRIMES):
        field_ = jets.ModP(p)
        rows, point, prog = codistribution_rows(system, field_, seed=seed * 2 + i)
        rank, order = _rank_by_order(rows, p)
        results.append((rank, order, rows.reshape(-1, n), point, prog, field_))
    ranks = (results[0][0], results[1][0])
    if ranks[0] != ranks[1]:
        log.warning("%s: ranks %d and %d at the two points; keeping the larger", system.name, *ranks)
    best = max(range(2), key=lambda i: results[i][0])
    rank, order = results[best][0], results[best][1]
    dirs: tuple[Direction, ...] = ()
    if directions and rank < n:
        dirs = _directions(system, results[best], results[1 - best], n - rank)
    return ObservabilityReport(
        name=system.name,
        state_names=system.state_names,
        rank=rank,
        ranks=ranks,
        derivative_order=order,
        directions=dirs,
        seconds=time.perf_counter() - t0,
        meta=dict(system.meta),
    )


def _support(names, v) -> tuple[str, ...]:
    return tuple(nm for nm, c in zip(names, v) if int(c) != 0)


def _directions(system: System, main, other, unobservable: int) -> tuple[Direction, ...]:
    """Readings of a basis of the kernel (see module doc)."""
    _, _, M, point, prog, field_ = main
    _, _, M2, point2, prog2, field2 = other
    p = field_.p
    names = system.state_names
    n = len(names)
    accepted: list[np.ndarray] = []
    out: list[Direction] = []

    def independent(v) -> bool:
        return rank_mod_p(np.array(accepted + [v]), p) == len(accepted) + 1

    for i, sym in enumerate(system.symmetries):
        if len(accepted) == unobservable:
            break
        try:
            v = jets.evaluate_values(prog, field_, point, f"sym{i}")
            v2 = jets.evaluate_values(prog2, field2, point2, f"sym{i}")
        except ZeroDivisionError:  # pragma: no cover
            continue
        if not v.any() or not _in_kernel(M, v, p) or not _in_kernel(M2, v2, field2.p):
            continue
        if independent(v):
            accepted.append(v)
            comps = tuple((nm, c) for nm, c in zip(names, sym.field) if c != 0)
            out.append(Direction(sym.kind, sym.reading, _support(names, v), comps))

    cols = [names.index(str(s)) for s in reversed(system.input_states)]  # highest derivatives first
    if cols and len(accepted) < unobservable:
        for w in nullspace_mod_p(M[:, cols], p, len(cols)):
            if len(accepted) == unobservable:
                break
            v = np.zeros(n, dtype=np.int64)
            v[cols] = w
            if independent(v):
                accepted.append(v)
                support = _support(names, v)
                out.append(Direction(DirectionKind.INPUT, "unknown-input direction: changes only " + ", ".join(support),
                                     support))
    if len(accepted) < unobservable:
        for v in nullspace_mod_p(M, p, n):
            if len(accepted) == unobservable:
                break
            if independent(v):
                accepted.append(v)
                support = _support(names, v)
                out.append(Direction(DirectionKind.OTHER, "unidentified direction in " + ", ".join(support), support))
    return tuple(out)


def float_rank(system: System, *, seed: int = 0, rtol: float | None = None) -> int:
    """Baseline only: the same rows in float64 at a random real point, rank by SVD (rows normalised)."""
    rows, _, _ = codistribution_rows(system, jets.Real(), seed=seed)
    M = rows.reshape(-1, system.dimension)
    norms = np.linalg.norm(M, axis=1)
    M = M[norms > 0] / norms[norms > 0, None]
    if M.size == 0:
        return 0
    return int(np.linalg.matrix_rank(M, rtol=rtol) if rtol is not None else np.linalg.matrix_rank(M))


def symbolic_rank(system, depth: int, seed: int = 1) -> int:
    """Baseline and independent check: the textbook route — iterated symbolic Lie derivatives (sympy,
    pruned to the ones that raise the rank), exact rank over Q at one random rational point."""
    rnd = random.Random(seed)
    theta = system.angles[0]
    t = sp.Rational(rnd.randint(1, 50), rnd.randint(51, 100))
    c, s = (1 - t**2) / (1 + t**2), 2 * t / (1 + t**2)
    point = {v: sp.Rational(rnd.randint(-50, 50), rnd.randint(1, 20)) for v in (*system.states, *system.params) if v != theta}
    fields = [sp.Matrix(g) for g in system.known_fields]
    if any(e != 0 for e in system.drift):
        fields.insert(0, sp.Matrix(system.drift))

    def row(fn):
        return [sp.diff(fn, v).subs({sp.cos(theta): c, sp.sin(theta): s}).subs(point) for v in system.states]

    M = sp.Matrix([row(h) for h in system.outputs])
    rank, level = M.rank(), list(system.outputs)
    for _ in range(depth):
        new = []
        for fn in level:
            for g in fields:
                L = sum((sp.diff(fn, v) * g[i] for i, v in enumerate(system.states)), sp.Integer(0))
                M2 = M.col_join(sp.Matrix([row(L)]))
                if M2.rank() > rank:
                    M, rank = M2, rank + 1
                    new.append(L)
        if not new:
            break
        level = new
    return rank


# ----------------------------------------------------------------------------- the table
#: The thesis' configurations: name -> (markers, targets, half markers).
TABLE_CONFIGURATIONS: dict[str, tuple[int, int, int]] = {
    "3 markers": (3, 0, 0),
    "2 markers": (2, 0, 0),
    "1.5 markers": (1, 0, 1),
    "1 marker": (1, 0, 0),
    "half marker + half target": (0, 0, 1),
    "1 target": (0, 1, 0),
    "2 targets": (0, 2, 0),
}


@dataclass(frozen=True)
class TableRow:
    """One row of the table: unobservable dimensions for known inputs and for unknown inputs under
    readings (A) and (P) at orders ``k = 0 .. len - 1``; ``dimensions``: the matching state
    dimensions (known, then A per k; P has the same dimensions as A)."""

    configuration: str
    vehicle: VehicleKind
    known: int
    analytic: tuple[int, ...]
    polynomial: tuple[int, ...]
    dimensions: tuple[int, ...]
    confirmed: bool

    def to_dict(self) -> dict:
        return {
            "configuration": self.configuration,
            "vehicle": self.vehicle.value,
            "known_inputs": self.known,
            "unknown_analytic": list(self.analytic),
            "unknown_polynomial": list(self.polynomial),
            "state_dimensions": list(self.dimensions),
            "confirmed": self.confirmed,
        }


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/topomap/observability`` (``~/.cache/...`` by default)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "topomap" / "observability"


def _cell(args: tuple) -> tuple[int, int, bool]:
    vehicle, m, t, h, inputs, reading, k, seed = args
    system = vehicle_landmark_system(vehicle, m, t, h, inputs, reading, k)
    rep = analyze(system, seed=seed, directions=False)
    return rep.unobservable_dimension, rep.state_dimension, rep.confirmed


def observability_table(
    vehicles: Iterable[str | VehicleKind] = ("unicycle", "omni"),
    orders: int = 4,
    *,
    configurations: Sequence[str] | None = None,
    seed: int = 0,
    workers: int = 1,
    cache_dir: Path | None = None,
    on_progress: Callable[[int, int], None] | None = None,
) -> list[TableRow]:
    """The thesis' table, each cell by :func:`analyze` (no directions); cells cached in ``cache_dir``."""
    kinds = [vehicle_kind(v) for v in vehicles]
    names = list(configurations) if configurations is not None else list(TABLE_CONFIGURATIONS)
    for nm in names:
        if nm not in TABLE_CONFIGURATIONS:
            raise unknown_choice("configuration", nm, TABLE_CONFIGURATIONS)
    if not isinstance(orders, int) or not 1 <= orders <= 8:
        raise ConfigError(f"orders={orders!r} must be an integer in 1..8")
    cells = []
    for kind in kinds:
        for nm in names:
            m, t, h = TABLE_CONFIGURATIONS[nm]
            cells.append((kind.value, m, t, h, "known", "analytic", 0, seed))
            for reading in ("analytic", "polynomial"):
                for k in range(orders):
                    cells.append((kind.value, m, t, h, "unknown", reading, k, seed))
    cache: dict = {}
    cache_file = None
    if cache_dir is not None:
        cache_file = Path(cache_dir) / f"table-v{ALGORITHM_VERSION}.json"
        try:
            cache = json.loads(cache_file.read_text())
        except (OSError, ValueError):
            cache = {}
    key = lambda c: "/".join(map(str, c))  # noqa: E731
    todo = [c for c in cells if key(c) not in cache]
    done = len(cells) - len(todo)
    if on_progress:
        on_progress(done, len(cells))
    if todo:
        # largest systems first so the pool stays busy
        todo.sort(key=lambda c: -(c[1] + 2 * c[2] + c[3] + (c[6] if c[4] == "unknown" else 0)))
        if workers > 1:
            with ProcessPoolExecutor(max_workers=workers) as pool:
                for c, res in zip(todo, pool.map(_cell, todo)):
                    cache[key(c)] = list(res)
                    done += 1
                    if on_progress:
                        on_progress(done, len(cells))
        else:
            for c in todo:
                cache[key(c)] = list(_cell(c))
                done += 1
                if on_progress:
                    on_progress(done, len(cells))
        if cache_file is not None:
            try:
                cache_file.parent.mkdir(parents=True, exist_ok=True)
                tmp = cache_file.with_suffix(".tmp")
                tmp.write_text(json.dumps(cache, indent=0, sort_keys=True))
                tmp.replace(cache_file)
            except OSError as e:  # a cache that cannot be written is not an error
                log.warning("could not write the observability cache %s: %s", cache_file, e)
    rows = []
    for kind in kinds:
        for nm in names:
            m, t, h = TABLE_CONFIGURATIONS[nm]
            known = cache[key((kind.value, m, t, h, "known", "analytic", 0, seed))]
            an = [cache[key((kind.value, m, t, h, "unknown", "analytic", k, seed))] for k in range(orders)]
            po = [cache[key((kind.value, m, t, h, "unknown", "polynomial", k, seed))] for k in range(orders)]
            rows.append(
                TableRow(
                    configuration=nm,
                    vehicle=kind,
                    known=known[0],
                    analytic=tuple(c[0] for c in an),
                    polynomial=tuple(c[0] for c in po),
                    dimensions=(known[1], *(c[1] for c in an)),
                    confirmed=bool(known[2] and all(c[2] for c in an + po)),
                )
            )
    return rows
