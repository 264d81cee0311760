"""System descriptions for the observability analysis (docs/theory.md sections 1-2).

A :class:`System` is a sympy description ``x' = f(x) + G(x) u + B(x) d``, ``y = h(x)`` with known
inputs ``u`` and unknown inputs ``d``. :func:`augment` turns the unknown inputs into states
``(d, d', ..., d^(k))`` under reading (A) or (P); :func:`vehicle_landmark_system` builds the bearing
systems of the thesis' table and :func:`linear_system` the scalar sanity system
``x' = a x + b d, y = c x``. Both go through the same analysis code.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field, replace
from fractions import Fraction

import sympy as sp

from topomap.errors import ConfigError, parse_enum
from topomap.motion import VehicleKind, vehicle_kind

__all__ = [
    "InputKind",
    "Reading",
    "DirectionKind",
    "Symmetry",
    "System",
    "augment",
    "input_kind",
    "reading_kind",
    "vehicle_landmark_system",
    "linear_system",
    "MAX_ORDER",
    "MAX_LANDMARKS",
]

MAX_ORDER = 8  # highest augmentation order k accepted
MAX_LANDMARKS = 6  # landmarks per configuration


class InputKind(str, enum.Enum):
    """Whether the vehicle's inputs are measured (odometry) or unknown (appearance only)."""

    KNOWN = "known"  # unknown-state observability (USO)
    UNKNOWN = "unknown"  # unknown-input observability (UIO): u + d unknown


class Reading(str, enum.Enum):
    """How the unknown inputs are modelled after augmentation to order k (docs/theory.md section 2)."""

    ANALYTIC = "analytic"  # (A): d^(k+1) unknown, output derivatives up to order k + 1 only
    POLYNOMIAL = "polynomial"  # (P): d^(k+1) = 0, every Lie derivative allowed


class DirectionKind(str, enum.Enum):
    """What an unobservable direction is, when it matches a known symmetry."""

    ROTATION = "rotation"
    TRANSLATION = "translation"
    SCALE = "scale"
    INPUT = "input"  # changes only the unknown inputs and their derivatives
    OTHER = "other"


def input_kind(name: str | InputKind) -> InputKind:
    """Parse ``known`` / ``unknown``; an unknown value lists the choices."""
    return parse_enum(InputKind, name, "inputs")


_READING_ALIASES = {"a": Reading.ANALYTIC, "p": Reading.POLYNOMIAL}


def reading_kind(name: str | Reading) -> Reading:
    """Parse ``analytic`` (``A``) / ``polynomial`` (``P``); an unknown value lists the choices."""
    if not isinstance(name, Reading) and str(name).lower() in _READING_ALIASES:
        return _READING_ALIASES[str(name).lower()]
    return parse_enum(Reading, name, "reading")


@dataclass(frozen=True)
class Symmetry:
    """A candidate unobservable vector field with its human reading.

    ``field``: one sympy component per state of the system it belongs to; ``input_action``: for each
    unknown input ``d_i`` the factor ``c_i`` with which the symmetry moves it (``delta d_i = c_i d_i``,
    and likewise every derivative of ``d_i``), used by :func:`augment` to extend the field.
    """

    kind: DirectionKind
    reading: str
    field: tuple
    input_action: tuple = ()


@dataclass(frozen=True)
class System:
    """``x' = f(x) + sum_j G_j(x) u_j + sum_i B_i(x) d_i``, ``y = h(x)`` in sympy.

    ``states``: ``(n,)`` Symbols; ``drift``: ``(n,)`` Exprs ``f``; ``known_fields``: ``(m_u, n)``
    (the columns ``G_j``), ``unknown_fields``: ``(m_d, n)`` (the columns ``B_i``, named by
    ``unknown_names``); ``outputs``: ``(p,)`` Exprs ``h``; ``params``: known constants, sampled at
    generic values; ``angles``: states that enter only through cos/sin (headings) or additively
    (bearings). After :func:`augment`: ``input_states`` are the disturbance states and
    ``max_derivative`` the highest output derivative allowed (reading A), ``None`` if unlimited.
    """

    name: str
    states: tuple
    drift: tuple
    outputs: tuple
    known_fields: tuple = ()
    unknown_fields: tuple = ()
    unknown_names: tuple = ()
    params: tuple = ()
    angles: tuple = ()
    input_states: tuple = ()
    max_derivative: int | None = None
    symmetries: tuple = ()
    meta: dict = field(default_factory=dict, compare=False, hash=False)

    def __post_init__(self) -> None:
        n = len(self.states)
        if n == 0:
            raise ConfigError("a system needs at least one state")
        if len(self.drift) != n:
            raise ConfigError(f"drift has {len(self.drift)} components for {n} states")
        if not self.outputs:
            raise ConfigError("a system needs at least one output")
        for fld in (*self.known_fields, *self.unknown_fields):
            if len(fld) != n:
                raise ConfigError(f"an input field has {len(fld)} components for {n} states")
        if self.unknown_names and len(self.unknown_names) != len(self.unknown_fields):
            raise ConfigError("unknown_names must name every unknown input field")
        for sym in self.symmetries:
            if len(sym.field) != n:
                raise ConfigError(f"symmetry {sym.reading!r} has {len(sym.field)} components for {n} states")
        for a in self.angles:
            if a not in self.states:
                raise ConfigError(f"angle {a} is not a state")

    @property
    def state_names(self) -> tuple[str, ...]:
        return tuple(str(s) for s in self.states)

    @property
    def dimension(self) -> int:
        return len(self.states)


def _derivative_name(base: str, j: int) -> str:
    return base + "'" * j if j <= 3 else f"{base}^({j})"


def augment(system: System, order: int, reading: str | Reading) -> System:
    """Unknown inputs become states: ``x_e = (x, d, d', ..., d^(k))`` (docs/theory.md section 2).

    Drift ``(f + B d, d', ..., d^(k), 0)``. Reading (A) allows output derivatives up to ``k + 1``
    only (``max_derivative``); reading (P) takes ``d^(k+1) = 0`` and allows all of them.
    """
    reading = reading_kind(reading)
    if not isinstance(order, int) or not 0 <= order <= MAX_ORDER:
        raise ConfigError(f"order={order!r} must be an integer in 0..{MAX_ORDER}")
    if not system.unknown_fields:
        raise ConfigError(f"system {system.name!r} has no unknown inputs to augment")
    m = len(system.unknown_fields)
    names = system.unknown_names or tuple(f"d{i + 1}" for i in range(m))
    blocks = [[sp.Symbol(_derivative_name(names[i], j), real=True) for i in range(m)] for j in range(order + 1)]
    d = blocks[0]
    n = system.dimension
    drift = [
        system.drift[r] + sum((system.unknown_fields[i][r] * d[i] for i in range(m)), sp.Integer(0)) for r in range(n)
    ]
    for j in range(order + 1):
        drift += [blocks[j + 1][i] if j < order else sp.Integer(0) for i in range(m)]
    new_states = [s for block in blocks for s in block]
    symmetries = []
    for sym in system.symmetries:
        action = sym.input_action or (0,) * m
        ext = [action[i] * blocks[j][i] for j in range(order + 1) for i in range(m)]
        symmetries.append(replace(sym, field=tuple(sym.field) + tuple(sp.sympify(e) for e in ext)))
    zero = (sp.Integer(0),) * len(new_states)
    return replace(
        system,
        name=f"{system.name}, unknown inputs ({reading.value}, k={order})",
        states=tuple(system.states) + tuple(new_states),
        drift=tuple(drift),
        known_fields=tuple(tuple(g) + zero for g in system.known_fields),
        unknown_fields=(),
        unknown_names=(),
        input_states=tuple(system.input_states) + tuple(new_states),
        max_derivative=order + 1 if reading is Reading.ANALYTIC else None,
        symmetries=tuple(symmetries),
        meta={**system.meta, "inputs": InputKind.UNKNOWN.value, "reading": reading.value, "order": order},
    )


# ----------------------------------------------------------------------------- vehicle + landmarks
def _count(name: str, value) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ConfigError(f"{name}={value!r} must be a non-negative integer")
    return value


def vehicle_landmark_system(
    vehicle: str | VehicleKind = "unicycle",
    markers: int = 1,
    targets: int = 0,
    half_markers: int = 0,
    inputs: str | InputKind = "unknown",
    reading: str | Reading = "analytic",
    order: int = 0,
) -> System:
    """The bearing-only system of a vehicle among landmarks (docs/theory.md sections 1-2).

    State ``(x, z, theta)`` with ``xi' = G(theta)(u + d)`` (eq. 1.7-1.8; the unicycle has no
    sideways channel), plus the unknown coordinates of the landmarks: a *marker* ``m_i`` is known
    (parameters ``x_mi, z_mi``), a *target* ``t_i`` unknown (states ``x_ti, z_ti`` with zero
    dynamics), a *half marker* ``h_i`` has its x known (parameter) and its z unknown (state).
    Outputs: the bearing of every landmark in the vehicle frame, ``atan2(z_L - z, x_L - x) - theta``.
    With ``inputs="known"`` the inputs are measured (``reading``/``order`` are ignored); with
    ``"unknown"`` the whole input ``u + d`` is unknown and the system is augmented to ``order``.
    """
    kind = vehicle_kind(vehicle)
    inputs = input_kind(inputs)
    reading = reading_kind(reading)
    markers = _count("markers", markers)
    targets = _count("targets", targets)
    half_markers = _count("half_markers", half_markers)
    total = markers + targets + half_markers
    if total == 0:
        raise ConfigError("no landmark: give at least one marker, target or half marker")
    if total > MAX_LANDMARKS:
        raise ConfigError(f"{total} landmarks is more than the {MAX_LANDMARKS} this analysis accepts")
    if not isinstance(order, int) or isinstance(order, bool) or not 0 <= order <= MAX_ORDER:
        raise ConfigError(f"order={order!r} must be an integer in 0..{MAX_ORDER}")

    R = dict(real=True)
    x, z, theta = sp.symbols("x z theta", **R)
    states = [x, z, theta]
    params = []
    landmarks = []  # (label, x expr, z expr)
    for i in range(markers):
        xm, zm = sp.symbols(f"x_m{i + 1} z_m{i + 1}", **R)
        params += [xm, zm]
        landmarks.append((f"marker m{i + 1}", xm, zm))
    for i in range(half_markers):
        xh, zh = sp.symbols(f"x_h{i + 1} z_h{i + 1}", **R)
        params.append(xh)
        states.append(zh)
        landmarks.append((f"half marker h{i + 1}", xh, zh))
    for i in range(targets):
        xt, zt = sp.symbols(f"x_t{i + 1} z_t{i + 1}", **R)
        states += [xt, zt]
        landmarks.append((f"target t{i + 1}", xt, zt))
    n = len(states)
    zeros = [sp.Integer(0)] * (n - 3)
    c, s = sp.cos(theta), sp.sin(theta)
    # columns of G(theta) (eq. 1.7-1.8): forward, sideways (omni only), turning
    columns = [("f", [c, s, 0]), ("h", [-s, c, 0]), ("w", [0, 0, 1])]
    if kind is VehicleKind.UNICYCLE:
        columns = [columns[0], columns[2]]
    fields = tuple(tuple(sp.sympify(v) for v in col) + tuple(zeros) for _, col in columns)
    # bearing of each landmark in the vehicle frame (beta of eq. 1.9 for a landmark at O)
    outputs = tuple(sp.atan2(zl - z, xl - x) - theta for _, xl, zl in landmarks)

    # candidate symmetries over every coordinate (states and known ones); dropped when they move a known one
    points = [(x, z)] + [(xl, zl) for _, xl, zl in landmarks]
    linear = tuple(1 if name in ("f", "h") else 0 for name, _ in columns)
    angular = (0,) * len(columns)
    candidates = []
    for label, xl, zl in landmarks:
        candidates.append((DirectionKind.ROTATION, f"rotation of the scene about {label}",
                           {px: -(pz - zl) for px, pz in points} | {pz: px - xl for px, pz in points} | {theta: 1},
                           angular))
    candidates.append((DirectionKind.TRANSLATION, "translation of the scene along x", {px: 1 for px, _ in points}, angular))
    candidates.append((DirectionKind.TRANSLATION, "translation of the scene along z", {pz: 1 for _, pz in points}, angular))
    for label, xl, zl in landmarks:
        candidates.append((DirectionKind.SCALE, f"scaling of positions and linear velocities about {label}",
                           {px: px - xl for px, _ in points} | {pz: pz - zl for _, pz in points}, linear))
    symmetries = []
    for kind_, text, comp, action in candidates:
        if any(sp.simplify(comp.get(p, 0)) != 0 for p in params):
            continue  # would move a known coordinate
        if all(sp.simplify(comp.get(st, 0)) == 0 for st in states):
            continue
        symmetries.append(Symmetry(kind_, text, tuple(sp.sympify(comp.get(st, 0)) for st in states), action))

    label = f"{kind.value}: {markers} marker(s), {half_markers} half marker(s), {targets} target(s)"
    base = System(
        name=label,
        states=tuple(states),
        drift=tuple([sp.Integer(0)] * n),
        outputs=outputs,
        params=tuple(params),
        angles=(theta,),
        symmetries=tuple(symmetries),
        meta={"vehicle": kind.value, "markers": markers, "targets": targets, "half_markers": half_markers},
    )
    if inputs is InputKind.KNOWN:
        return replace(base, name=label + ", known inputs", known_fields=fields, meta={**base.meta, "inputs": "known"})
    base = replace(base, unknown_fields=fields, unknown_names=tuple(f"d_{name}" for name, _ in columns))
    return augment(base, order, reading)


def _rational(name: str, value) -> sp.Rational:
    try:
        return sp.Rational(Fraction(str(value)))
    except (ValueError, TypeError, ZeroDivisionError):
        raise ConfigError(f"{name}={value!r} is not a number") from None


def linear_system(a=1, b=1, c=1, inputs: str | InputKind = "unknown", reading: str | Reading = "analytic",
                  order: int = 0) -> System:
    """The scalar sanity system ``x' = a x + b d``, ``y = c x`` (coefficients taken as exact rationals)."""
    a, b, c = (_rational(nm, v) for nm, v in (("a", a), ("b", b), ("c", c)))
    x = sp.Symbol("x", real=True)
    base = System(name=f"linear a={a} b={b} c={c}", states=(x,), drift=(a * x,), outputs=(c * x,),
                  meta={"a": str(a), "b": str(b), "c": str(c)})
    if input_kind(inputs) is InputKind.KNOWN:
        return replace(base, known_fields=((b,),), name=base.name + ", known input")
    return augment(replace(base, unknown_fields=((b,),), unknown_names=("d",)), order, reading)

