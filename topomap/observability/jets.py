"""Lie derivatives at a point by Taylor-mode automatic differentiation, exactly over GF(p).

Along the flow ``x(t)`` of the drift, ``L_f^j h(x0) = j! [t^j] h(x(t))``; carrying with every Taylor
coefficient its gradient with respect to ``x0`` (dual numbers) gives the rows ``d L_f^j h (x0)`` of the
observability codistribution (docs/theory.md section 2) without ever forming ``L_f^j h`` symbolically.
Hand-written because symbolic Lie derivatives of bearings swell past sympy's reach beyond order ~5,
and no maintained library does Taylor-mode differentiation over a finite field.

Arithmetic is in GF(p) (:class:`ModP`, exact: rank mod p at a random point is a lower bound of the
generic rank, equal to it with probability ``>= 1 - degree / p``) or in float64 (:class:`Real`, only
the baseline of the benchmark). Known inputs enter as polynomials in t with random coefficients, one
batch entry per input sample: the span of the resulting rows is the span of all iterated Lie
derivatives along the known-input fields.

Supported expressions (sympy): rational constants, parameters, states, known inputs, ``+``, ``*``,
``/``, integer powers, ``cos``/``sin`` of an *angle state* and ``atan2``. The value of an angle state
and of an ``atan2`` is transcendental at a rational point, so it is carried as *opaque* (unknown value,
exact gradient and exact higher coefficients): opaque terms may only be added (bearings), never
multiplied. Angle states are evaluated through a rational point of the unit circle
``(cos, sin) = ((1 - t^2) / (1 + t^2), 2 t / (1 + t^2))``, so every entry stays exact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import sympy as sp

from topomap.errors import ConfigError

__all__ = ["ModP", "Real", "Program", "compile_program", "Point", "sample_point", "lie_rows", "evaluate_values"]


# ----------------------------------------------------------------------------- fields
class ModP:
    """GF(p) on int64 arrays; p < 2**30 so a sum of two products never overflows."""

    exact = True

    def __init__(self, p: int) -> None:
        if not (2 < p < 2**30):
            raise ValueError("prime must lie in (2, 2**30)")
        self.p = int(p)
        self.dtype = np.int64

    def red(self, a):
        return a % self.p

    def mul(self, a, b):
        return (a * b) % self.p

    def const(self, q) -> int:
        q = sp.Rational(q)
        return (int(q.p) % self.p) * pow(int(q.q) % self.p, -1, self.p) % self.p

    def inv(self, a: np.ndarray) -> np.ndarray:
        flat = [int(v) % self.p for v in np.ravel(a)]
        if 0 in flat:
            raise ZeroDivisionError("division by zero at the sampled point")
        return np.array([pow(v, -1, self.p) for v in flat], dtype=np.int64).reshape(np.shape(a))

    def random(self, rng: np.random.Generator, size) -> np.ndarray:
        return rng.integers(1, self.p, size=size, dtype=np.int64)


class Real:
    """float64 arithmetic: the floating-point baseline only."""

    exact = False

    def __init__(self) -> None:
        self.dtype = np.float64

    def red(self, a):
        return a

    def mul(self, a, b):
        return a * b

    def const(self, q) -> float:
        return float(q)

    def inv(self, a):
        if np.any(a == 0):
            raise ZeroDivisionError("division by zero at the sampled point")
        return 1.0 / a

    def random(self, rng: np.random.Generator, size) -> np.ndarray:
        return rng.uniform(-2.0, 2.0, size=size)


# ----------------------------------------------------------------------------- program
@dataclass
class _Node:
    op: str  # state | param | input | const | add | mul | div | cos | sin | atan2
    args: tuple = ()
    coeffs: tuple = ()  # add: rational coefficients of args
    const: object = None  # const: sympy Rational
    index: int = -1  # state / param / input index
    opaque: bool = False  # coefficient-0 value unknown (transcendental)
    constant: bool = False  # same value for all t (params, constants)


@dataclass
class Program:
    """A straight-line program over the nodes of a set of sympy expressions (shared subexpressions once)."""

    nodes: list
    states: tuple
    params: tuple
    inputs: tuple
    angles: tuple  # indices into states
    roots: dict  # name -> list of node ids


def compile_program(states, params, inputs, angles, roots: dict) -> Program:
    """Compile the sympy expressions of ``roots`` (name -> list of Expr) into one :class:`Program`."""
    states = tuple(states)
    params = tuple(params)
    inputs = tuple(inputs)
    sidx = {s: i for i, s in enumerate(states)}
    pidx = {s: i for i, s in enumerate(params)}
    uidx = {s: i for i, s in enumerate(inputs)}
    angle_idx = tuple(sidx[a] for a in angles)
    nodes: list[_Node] = []
    memo: dict = {}

    def add_node(node: _Node) -> int:
        nodes.append(node)
        return len(nodes) - 1

    def const_node(q) -> int:
        key = ("const", sp.Rational(q))
        if key not in memo:
            memo[key] = add_node(_Node("const", const=sp.Rational(q), constant=True))
        return memo[key]

    def unsupported(e, why):
        return ConfigError(f"expression {e} is not supported by the exact evaluator ({why}); rewrite the system")

    def mul2(a: int, b: int, e) -> int:
        if nodes[a].opaque or nodes[b].opaque:
            raise unsupported(e, "a bearing or angle may only be added, not multiplied")
        return add_node(_Node("mul", (a, b), constant=nodes[a].constant and nodes[b].constant))

    def power(base: int, n: int, e) -> int:
        if n == 0:
            return const_node(1)
        if n < 0:
            inv = add_node(_Node("div", (const_node(1), power(base, -n, e)), constant=nodes[base].constant))
            if nodes[base].opaque:
                raise unsupported(e, "a bearing or angle may only be added")
            return inv
        result, sq = None, base
        while n:  # square and multiply
            if n & 1:
                result = sq if result is None else mul2(result, sq, e)
            n >>= 1
            if n:
                sq = mul2(sq, sq, e)
        return result

    def visit(e) -> int:
        if e in memo:
            return memo[e]
        if e in sidx:
            i = sidx[e]
            out = add_node(_Node("state", index=i, opaque=i in angle_idx))
        elif e in pidx:
            out = add_node(_Node("param", index=pidx[e], constant=True))
        elif e in uidx:
            out = add_node(_Node("input", index=uidx[e]))
        elif e.is_Rational:
            out = const_node(e)
        elif e.is_Add:
            args, coeffs = [], []
            for term in e.args:
                c, rest = term.as_coeff_Mul()
                if rest == 1:
                    args.append(const_node(c))
                    coeffs.append(sp.Integer(1))
                else:
                    args.append(visit(rest))
                    coeffs.append(sp.Rational(c))
            out = add_node(
                _Node("add", tuple(args), tuple(coeffs), opaque=any(nodes[a].opaque for a in args),
                      constant=all(nodes[a].constant for a in args))
            )
        elif e.is_Mul:
            c, rest = e.as_coeff_Mul()
            if c != 1:
                r = visit(rest)
                out = add_node(_Node("add", (r,), (sp.Rational(c),), opaque=nodes[r].opaque, constant=nodes[r].constant))
            else:
                factors = [visit(a) for a in e.args]
                out = factors[0]
                for f in factors[1:]:
                    out = mul2(out, f, e)
        elif e.is_Pow:
            base, ex = e.args
            if not ex.is_Integer:
                raise unsupported(e, "only integer powers")
            out = power(visit(base), int(ex), e)
        elif isinstance(e, (sp.cos, sp.sin)):
            arg = e.args[0]
            if arg not in sidx or sidx[arg] not in angle_idx:
                raise unsupported(e, "cos/sin only of an angle state")
            a = visit(arg)
            out = add_node(_Node("cos" if isinstance(e, sp.cos) else "sin", (a,)))
        elif isinstance(e, sp.atan2):
            y, x = (visit(a) for a in e.args)
            if nodes[y].opaque or nodes[x].opaque:
                raise unsupported(e, "atan2 of an angle")
            out = add_node(_Node("atan2", (y, x)))
        else:
            raise unsupported(e, f"function {type(e).__name__}")
        memo[e] = out
        return out

    compiled = {name: [visit(sp.sympify(e)) for e in exprs] for name, exprs in roots.items()}
    return Program(nodes, states, params, inputs, angle_idx, compiled)


# ----------------------------------------------------------------------------- point
@dataclass
class Point:
    """A sampled point: states ``(n,)``, params ``(q,)``, angle (cos, sin) ``(a, 2)``, known-input
    polynomial coefficients ``(B, J + 1, m)`` (``B`` samples), all in the field's dtype."""

    states: np.ndarray
    params: np.ndarray
    trig: np.ndarray
    inputs: np.ndarray


def sample_point(program: Program, field, rng: np.random.Generator, samples: int, order: int) -> Point:
    """A random point of state/parameter space and ``samples`` random known-input jets up to ``order``."""
    n, q, m = len(program.states), len(program.params), len(program.inputs)
    states = field.random(rng, n)
    trig = np.zeros((len(program.angles), 2), dtype=field.dtype)
    for a, i in enumerate(program.angles):
        if field.exact:  # rational point of the unit circle: (1 - t^2, 2 t) / (1 + t^2)
            while True:
                t = int(field.random(rng, 1)[0])
                den = (1 + t * t) % field.p
                if den:
                    break
            inv = pow(den, -1, field.p)
            trig[a] = [((1 - t * t) % field.p) * inv % field.p, (2 * t) % field.p * inv % field.p]
            states[i] = 0  # opaque: never used
        else:
            theta = rng.uniform(-math.pi, math.pi)
            states[i] = theta
            trig[a] = [math.cos(theta), math.sin(theta)]
    params = field.random(rng, q)
    inputs = field.random(rng, (samples, order + 1, m)) if m else np.zeros((samples, order + 1, 0), field.dtype)
    if not field.exact:
        inputs = inputs / np.array([math.factorial(k) for k in range(order + 1)])[None, :, None]
    return Point(states, params, trig, inputs)


# ----------------------------------------------------------------------------- Taylor mode
def _conv(F, A, B, k: int, lo: int, hi: int):
    """sum_{i=lo}^{hi} A[i] (x) B[k - i] for dual coefficients (value, gradient) of shape (S, n + 1)."""
    if hi < lo:
        return np.zeros_like(A[0])
    a = A[lo : hi + 1]
    b = B[k - hi : k - lo + 1][::-1]
    out = np.empty_like(A[0])
    out[..., 0] = F.red(F.mul(a[..., 0], b[..., 0]).sum(axis=0))
    out[..., 1:] = F.red((F.mul(a[..., :1], b[..., 1:]) + F.mul(b[..., :1], a[..., 1:])).sum(axis=0))
    return out


def _ddiv(F, x, y0):
    """Dual division x / y0 for dual coefficients of shape (S, n + 1)."""
    inv = F.inv(y0[..., 0])[..., None]
    out = np.empty_like(x)
    out[..., :1] = F.mul(x[..., :1], inv)
    out[..., 1:] = F.mul(F.red(x[..., 1:] - F.mul(out[..., :1], y0[..., 1:])), inv)
    return out


def _scale(F, c, x):
    return F.mul(x, c)


def lie_rows(program: Program, field, point: Point, order: int, drift: str = "drift", outputs: str = "outputs"):
    """Gradients of the Taylor coefficients of the outputs along the flow of the drift.

    Returns ``rows: (order + 1, p, S, n)`` with ``rows[j, i, s] = d L^j h_i (x0) / j!`` for input
    sample ``s`` (exact in GF(p) for :class:`ModP`), and ``values: (order + 1, p, S)`` (coefficient
    0 of an opaque output is meaningless).
    """
    nodes = program.nodes
    n = len(program.states)
    S = point.inputs.shape[0]
    J = order
    if point.inputs.shape[1] < J + 1:
        raise ValueError("input jets shorter than the requested order")
    F = field
    dt = F.dtype
    aux: dict = {}
    drift_ids = program.roots[drift]
    out_ids = program.roots[outputs]
    series = [np.zeros((J + 1, S, n + 1), dtype=dt) for _ in nodes]
    angle_pos = {i: a for a, i in enumerate(program.angles)}
    inv_k = [None] + [F.const(sp.Rational(1, k)) for k in range(1, J + 2)]

    for k in range(J + 1):
        for idx, nd in enumerate(nodes):
            s = series[idx]
            op = nd.op
            if op == "state":
                if k == 0:  # later coefficients come from the flow, below
                    s[0, :, 0] = point.states[nd.index]
                    s[0, :, 1 + nd.index] = 1
            elif op == "param":
                if k == 0:
                    s[0, :, 0] = point.params[nd.index]
            elif op == "const":
                if k == 0:
                    s[0, :, 0] = F.const(nd.const)
            elif op == "input":
                s[k, :, 0] = point.inputs[:, k, nd.index]
            elif op == "add":
                acc = np.zeros((S, n + 1), dtype=dt)
                for a, c in zip(nd.args, nd.coeffs):
                    acc = acc + _scale(F, F.const(c), series[a][k])
                s[k] = F.red(acc)
            elif op == "mul":
                a, b = nd.args
                if nodes[a].constant:
                    s[k] = F.red(_conv(F, series[a], series[b], k, 0, 0))
                elif nodes[b].constant:
                    s[k] = F.red(_conv(F, series[a], series[b], k, k, k))
                else:
                    s[k] = _conv(F, series[a], series[b], k, 0, k)
            elif op == "div":
                a, b = nd.args
                acc = F.red(series[a][k] - _conv(F, s, series[b], k, 0, k - 1))
                s[k] = _ddiv(F, acc, series[b][0])
            elif op in ("cos", "sin"):
                theta = series[nd.args[0]]
                key = nd.args[0]
                trig = aux.setdefault(("trig", key), {})
                if k not in trig:
                    if "c" not in trig:
                        trig["c"] = np.zeros((J + 1, S, n + 1), dtype=dt)
                        trig["s"] = np.zeros((J + 1, S, n + 1), dtype=dt)
                    c, sn = trig["c"], trig["s"]
                    if k == 0:
                        ai = angle_pos[nodes[key].index]
                        c0, s0 = point.trig[ai]
                        c[0, :, 0] = c0
                        sn[0, :, 0] = s0
                        c[0, :, 1:] = F.red(-F.mul(theta[0, :, 1:], s0))
                        sn[0, :, 1:] = F.mul(theta[0, :, 1:], c0)
                    else:
                        # c' = -s theta', s' = c theta' (k c_k = -sum i theta_i s_{k-i})
                        itheta = F.red(theta[1 : k + 1] * np.arange(1, k + 1, dtype=dt)[:, None, None])
                        pad = np.concatenate([np.zeros_like(theta[:1]), itheta], axis=0)
                        c[k] = F.red(-F.mul(_conv(F, pad, sn, k, 1, k), inv_k[k]))
                        sn[k] = F.mul(_conv(F, pad, c, k, 1, k), inv_k[k])
                    trig[k] = True
                s[k] = trig["c" if op == "cos" else "s"][k]
            elif op == "atan2":
                y, x = (series[a] for a in nd.args)
                st = aux.setdefault(("atan2", idx), {
                    "r": np.zeros((J + 1, S, n + 1), dtype=dt),
                    "num": np.zeros((J + 1, S, n + 1), dtype=dt),
                    "q": np.zeros((J + 1, S, n + 1), dtype=dt),
                    "dy": np.zeros((J + 1, S, n + 1), dtype=dt),
                    "dx": np.zeros((J + 1, S, n + 1), dtype=dt),
                })
                r, num, q, dy, dx = st["r"], st["num"], st["q"], st["dy"], st["dx"]
                r[k] = F.red(_conv(F, x, x, k, 0, k) + _conv(F, y, y, k, 0, k))
                if k == 0:
                    if F.exact:
                        s[0, :, 0] = 0  # opaque
                    else:
                        s[0, :, 0] = np.arctan2(y[0, :, 0], x[0, :, 0])
                    g = F.red(F.mul(x[0, :, :1], y[0, :, 1:]) - F.mul(y[0, :, :1], x[0, :, 1:]))
                    s[0, :, 1:] = F.mul(g, F.inv(r[0, :, 0])[:, None])
                else:
                    # atan2' = (x y' - y x') / (x^2 + y^2): coefficient k from the quotient's k - 1
                    j = k - 1
                    dy[j] = F.mul(y[k], F.const(k))
                    dx[j] = F.mul(x[k], F.const(k))
                    num[j] = F.red(_conv(F, x, dy, j, 0, j) - _conv(F, y, dx, j, 0, j))
                    q[j] = _ddiv(F, F.red(num[j] - _conv(F, q, r, j, 0, j - 1)), r[0])
                    s[k] = F.mul(q[j], inv_k[k])
        if k < J:  # the flow: x_{k+1} = f_k / (k + 1)
            for idx, nd in enumerate(nodes):
                if nd.op == "state":
                    s_next = series[drift_ids[nd.index]][k]
                    series[idx][k + 1] = F.mul(s_next, inv_k[k + 1])
    rows = np.stack([series[o][:, :, 1:] for o in out_ids], axis=1)  # (J+1, p, S, n)
    values = np.stack([series[o][:, :, 0] for o in out_ids], axis=1)
    return rows, values


def evaluate_values(program: Program, field, point: Point, name: str) -> np.ndarray:
    """Values (coefficient 0) of the expressions ``program.roots[name]`` at ``point``: ``(len,)``."""
    _, values = lie_rows(program, field, Point(point.states, point.params, point.trig, point.inputs[:1, :1]), 0,
                         outputs=name)
    return values[0, :, 0]
