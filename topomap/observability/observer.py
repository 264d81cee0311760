"""Unknown-input observer for bearing-only vehicles (docs/theory.md section 2, observer, §2.5).

A high-gain differentiator estimates the output derivatives ``Z = (y, y', ..., y^(k+1))``; the
augmented state ``xi_e = (xi, landmarks, d, ..., d^(k))`` (reading A) follows

    xi_e_hat' = f_e(xi_e_hat) + J(xi_e_hat)^+ Gamma (Z_hat - Phi(xi_e_hat)),
    Phi = (h, L_f h, ..., L_f^{k+1} h),  J = dPhi / dxi_e,

with ``Phi`` and ``J`` differentiated symbolically (sympy) and evaluated with numpy. Where ``Phi``
is injective the error converges (ultimately bounded with time-varying inputs); along the kernel of
``J`` — the unobservable directions of :mod:`~topomap.observability.analysis` — nothing corrects it.
With ``inputs="known"`` it is the unknown-state observer: ``Phi = (h, L_{G u} h)`` with ``u``
measured.

:func:`simulate` runs it against a simulated vehicle with time-varying unknown inputs;
:func:`plot_simulation` draws the estimation errors (matplotlib, Agg canvas).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import sympy as sp

from topomap.errors import ConfigError, DatasetError
from topomap.motion import VehicleKind, vehicle_kind, wrap_angle
from topomap.observability.system import InputKind, input_kind, vehicle_landmark_system

__all__ = [
    "ObserverConfig",
    "Simulation",
    "LANDMARK_LAYOUT",
    "CONVERGENCE_TIME_S",
    "lie_derivatives",
    "simulate",
    "plot_simulation",
]

#: Landmark positions of the simulated scene [m]: markers take the first ones, then half markers,
#: then targets.
LANDMARK_LAYOUT: tuple[tuple[float, float], ...] = (
    (0.0, 5.0),
    (-4.5, -2.5),
    (4.5, -3.0),
    (5.0, 5.5),
    (-5.0, 4.5),
    (0.5, -6.0),
)

#: With the default :class:`ObserverConfig`, 3 markers and unknown time-varying inputs, the
#: estimation error stays below 5 % of its initial size from this time on [s] (both vehicles;
#: checked by the tests).
CONVERGENCE_TIME_S = 1.5


@dataclass(frozen=True)
class ObserverConfig:
    """Observer gains, scenario and initial estimation errors of :func:`simulate`."""

    order: int = 1  # augmentation order k (reading A): estimates d, ..., d^(k)
    epsilon_s: float = 0.02  # high-gain differentiator time scale [s]
    gain_per_s: float = 8.0  # Gamma = gain * identity [1/s]
    dt_s: float = 1e-3  # Euler step of vehicle, differentiator and observer [s]
    duration_s: float = 10.0  # simulated time [s]
    warmup_s: float = 0.25  # the observer only predicts while the differentiator settles [s]
    position_error_m: float = 0.5  # initial error of the vehicle and of each unknown landmark [m]
    heading_error_rad: float = 0.3  # initial heading error [rad]
    input_error: float = 0.2  # initial error of each input state [m/s, rad/s, their derivatives]
    pinv_rcond: float = 1e-4  # singular values of J below this fraction of the largest are ignored
    record_every: int = 10  # keep one sample in this many steps
    seed: int = 0  # direction of the initial errors

    def __post_init__(self) -> None:
        if isinstance(self.order, bool) or not isinstance(self.order, int) or not 0 <= self.order <= 3:
            raise ConfigError(f"observer order={self.order!r} must be an integer in 0..3")
        for name in ("epsilon_s", "gain_per_s", "dt_s", "duration_s"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name}={getattr(self, name)} must be positive")
        if self.dt_s > self.epsilon_s / 4:
            raise ConfigError(f"dt_s={self.dt_s} is too large for epsilon_s={self.epsilon_s}; use dt_s <= epsilon_s / 4")
        if self.duration_s / self.dt_s > 2e6:
            raise ConfigError("duration_s / dt_s is above 2e6 steps; shorten the run or enlarge dt_s")
        if self.record_every < 1:
            raise ConfigError("record_every must be at least 1")


@dataclass(frozen=True)
class Simulation:
    """Time series of one observer run (recorded every ``record_every`` steps).

    ``t: (T,) float64 [s]``; ``truth``, ``estimate``: ``(T, n) float64`` in the order of
    ``state_names``; ``bearings: (T, p) float64 [rad]`` measured (unwrapped);
    ``unobservable_error: (T,) float64``: norm of the error's component in the kernel of ``J`` at the
    true state; ``landmarks: (L, 2)`` true positions [m]; ``meta``: the scenario.
    """

    t: np.ndarray
    state_names: tuple[str, ...]
    truth: np.ndarray
    estimate: np.ndarray
    bearings: np.ndarray
    unobservable_error: np.ndarray
    landmarks: np.ndarray
    meta: dict = field(default_factory=dict)

    @property
    def error(self) -> np.ndarray:
        """``estimate - truth``, heading wrapped to [-pi, pi): ``(T, n)``."""
        e = self.estimate - self.truth
        i = self.state_names.index("theta")
        e[:, i] = wrap_angle(e[:, i])
        return e

    def group(self, name: str) -> np.ndarray:
        """Indices of the states of group ``pose`` | ``landmarks`` | ``inputs``."""
        idx = {
            "pose": [0, 1, 2],
            "inputs": [i for i, s in enumerate(self.state_names) if s.startswith("d_")],
        }
        idx["landmarks"] = [i for i in range(3, len(self.state_names)) if i not in idx["inputs"]]
        if name not in idx:
            raise ConfigError(f"unknown state group {name!r}; choose one of: inputs, landmarks, pose")
        return np.array(idx[name], dtype=int)

    def relative_error(self, group: str | None = None) -> np.ndarray:
        """``|e(t)| / |e(0)|`` over all states or one group: ``(T,)``."""
        e = self.error if group is None else self.error[:, self.group(group)]
        if e.shape[1] == 0:
            return np.zeros(len(self.t))
        n0 = np.linalg.norm(e[0])
        return np.linalg.norm(e, axis=1) / (n0 if n0 > 0 else 1.0)

    @property
    def rotation_error(self) -> np.ndarray:
        """Error along the rotation about the first landmark: ``phi_hat - phi`` with ``phi`` the
        vehicle's polar angle about it, ``(T,) [rad]``."""
        lx, lz = self.landmarks[0]
        phi = np.arctan2(self.truth[:, 1] - lz, self.truth[:, 0] - lx)
        phi_hat = np.arctan2(self.estimate[:, 1] - lz, self.estimate[:, 0] - lx)
        return wrap_angle(phi_hat - phi)

    def settling_time(self, threshold: float = 0.05) -> float | None:
        """First time after which the relative error stays below ``threshold`` (None if never)."""
        rel = self.relative_error()
        above = np.nonzero(~(rel < threshold))[0]
        if len(above) == 0:
            return float(self.t[0])
        if above[-1] == len(rel) - 1:
            return None
        return float(self.t[above[-1] + 1])

    def summary(self) -> dict:
        """A JSON-able digest: settling time, final relative errors, rotation error."""
        end = slice(-max(1, len(self.t) // 20), None)  # the last 5 % of the run
        rot = self.rotation_error
        return {
            **self.meta,
            "duration_s": float(self.t[-1]),
            "settling_time_s": self.settling_time(),
            "final_relative_error": float(np.max(self.relative_error()[end])),
            "final_relative_error_by_group": {
                g: float(np.max(self.relative_error(g)[end])) for g in ("pose", "landmarks", "inputs")
                if len(self.group(g))
            },
            "rotation_error_initial_rad": float(abs(rot[0])),
            "rotation_error_final_rad": float(np.max(np.abs(rot[end]))),
            "unobservable_error_final": float(np.max(self.unobservable_error[end])),
        }


# ----------------------------------------------------------------------------- symbolic part
def lie_derivatives(outputs, states, drift, order: int) -> list:
    """``[h, L_f h, ..., L_f^order h]`` flattened j-major (all outputs at order 0, then 1, ...), sympy."""
    X = sp.Matrix(states)
    F = sp.Matrix(drift)
    level = sp.Matrix(outputs)
    out = list(level)
    for _ in range(order):
        level = level.jacobian(X) * F
        out += list(level)
    return out


@dataclass
class _Model:
    n: int
    p: int
    rows: int  # derivative orders in Phi
    phi: object  # (states, u) -> (rows * p,)
    jac: object  # (states, u) -> (rows * p, n)
    drift: object  # (states, u) -> (n,)
    states: tuple


def _model(vehicle: VehicleKind, markers, targets, half_markers, inputs: InputKind, order: int, layout) -> _Model:
    system = vehicle_landmark_system(vehicle, markers, targets, half_markers, inputs, "analytic", order)
    values = {}
    positions = list(layout)
    # params: markers (x, z), then half markers (x) — in the order the builder made them
    k = 0
    for i in range(markers):
        values[f"x_m{i + 1}"], values[f"z_m{i + 1}"] = positions[k]
        k += 1
    for i in range(half_markers):
        values[f"x_h{i + 1}"] = positions[k][0]
        k += 1
    subs = {p: sp.Float(values[str(p)]) for p in system.params}
    states = tuple(system.states)
    if inputs is InputKind.KNOWN:
        u = sp.symbols(f"u0:{len(system.known_fields)}", real=True)
        drift = [sum((g[r] * u[j] for j, g in enumerate(system.known_fields)), sp.Integer(0)) for r in range(len(states))]
        phi = lie_derivatives(system.outputs, states, drift, 1)
    else:
        u = ()
        drift = list(system.drift)
        phi = lie_derivatives(system.outputs, states, drift, order + 1)
    phi = [e.subs(subs) for e in phi]
    jac = sp.Matrix(phi).jacobian(sp.Matrix(states))
    drift = [sp.sympify(e).subs(subs) for e in drift]
    args = (list(states), list(u) if u else [sp.Symbol("_none")])
    model = _Model(
        n=len(states),
        p=len(system.outputs),
        rows=len(phi) // len(system.outputs),
        phi=sp.lambdify(args, sp.Matrix(phi), "numpy", cse=True),
        jac=sp.lambdify(args, jac, "numpy", cse=True),
        drift=sp.lambdify(args, sp.Matrix(drift), "numpy", cse=True),
        states=tuple(str(s) for s in states),
    )
    return model


# ----------------------------------------------------------------------------- scenario
def _true_inputs(kind: VehicleKind, t: float, max_order: int) -> np.ndarray:
    """True (u + d)(t) and its derivatives, ``(max_order + 1, channels)``: smooth, time-varying."""
    # (offset, amplitude, angular frequency [rad/s], phase) per channel: v_f [m/s], v_h [m/s], omega [rad/s]
    chans = [(0.5, 0.15, 0.6, 0.0), (0.0, 0.2, 0.4, 1.0), (0.25, 0.1, 0.5, 0.5)]
    if kind is VehicleKind.UNICYCLE:
        chans = [chans[0], chans[2]]
    out = np.zeros((max_order + 1, len(chans)))
    for c, (off, amp, w, ph) in enumerate(chans):
        for j in range(max_order + 1):
            out[j, c] = (off if j == 0 else 0.0) + amp * w**j * math.sin(w * t + ph + j * math.pi / 2)
    return out


def simulate(
    vehicle: str | VehicleKind = "unicycle",
    markers: int = 3,
    targets: int = 0,
    half_markers: int = 0,
    inputs: str | InputKind = "unknown",
    config: ObserverConfig = ObserverConfig(),
) -> Simulation:
    """Run the observer against a simulated vehicle with time-varying inputs (see module doc).

    The vehicle starts at (1.5, 0) m heading along +z and drives loops among the landmarks of
    :data:`LANDMARK_LAYOUT`; its input ``u + d`` is unknown to the observer when ``inputs="unknown"``.
    """
    kind = vehicle_kind(vehicle)
    inputs = input_kind(inputs)
    vehicle_landmark_system(kind, markers, targets, half_markers, inputs)  # validates the counts
    total = markers + targets + half_markers
    if total > len(LANDMARK_LAYOUT):
        raise ConfigError(f"the simulated scene has {len(LANDMARK_LAYOUT)} landmarks; ask for at most that many")
    k = config.order
    model = _model(kind, markers, targets, half_markers, inputs, k, LANDMARK_LAYOUT[:total])
    n, p = model.n, model.p
    names = model.states
    landmarks = np.array(LANDMARK_LAYOUT[:total], dtype=float)
    channels = 2 if kind is VehicleKind.UNICYCLE else 3

    # true augmented state
    def truth_at(pose: np.ndarray, t: float) -> np.ndarray:
        x = np.zeros(n)
        x[:3] = pose
        j = 3
        for i in range(half_markers):
            x[j] = landmarks[markers + i][1]
            j += 1
        for i in range(targets):
            x[j : j + 2] = landmarks[markers + half_markers + i]
            j += 2
        if inputs is InputKind.UNKNOWN:
            x[j:] = _true_inputs(kind, t, k).ravel()
        return x

    rng = np.random.default_rng(config.seed)

    def unit(size):
        v = rng.normal(size=size)
        return v / np.linalg.norm(v)

    pose = np.array([1.5, 0.0, math.pi / 2])
    x_true = truth_at(pose, 0.0)
    x_hat = x_true.copy()
    x_hat[:2] += config.position_error_m * unit(2)
    x_hat[2] += config.heading_error_rad * (1 if rng.random() < 0.5 else -1)
    j = 3
    for _ in range(half_markers):
        x_hat[j] += config.position_error_m * (1 if rng.random() < 0.5 else -1)
        j += 1
    for _ in range(targets):
        x_hat[j : j + 2] += config.position_error_m * unit(2)
        j += 2
    if n > j:
        x_hat[j:] += config.input_error * np.sign(rng.normal(size=n - j))

    def bearings_of(xt: np.ndarray) -> np.ndarray:
        out = np.empty(p)
        for i in range(markers):
            lx, lz = landmarks[i]
            out[i] = math.atan2(lz - xt[1], lx - xt[0]) - xt[2]
        j = 3
        for i in range(half_markers):
            lx = landmarks[markers + i][0]
            out[markers + i] = math.atan2(xt[j] - xt[1], lx - xt[0]) - xt[2]
            j += 1
        for i in range(targets):
            out[markers + half_markers + i] = math.atan2(xt[j + 1] - xt[1], xt[j] - xt[0]) - xt[2]
            j += 2
        return out

    # high-gain differentiator per output: r = number of derivative orders in Phi
    r = model.rows
    alpha = np.array([math.comb(r, i) for i in range(1, r + 1)], dtype=float)
    eps_pow = config.epsilon_s ** np.arange(1, r + 1)
    y = bearings_of(x_true)
    zhat = np.zeros((r, p))
    zhat[0] = y
    gamma = config.gain_per_s
    dt = config.dt_s
    steps = int(round(config.duration_s / dt))
    rec = []
    none = np.zeros(1)

    def u_arg(t):
        if inputs is InputKind.KNOWN:
            return _true_inputs(kind, t, 0)[0]
        return none

    for step in range(steps + 1):
        t = step * dt
        x_true = truth_at(pose, t)
        y_new = bearings_of(x_true)
        y = y + wrap_angle(y_new - y)  # unwrapped measurement
        if step % config.record_every == 0:
            Jt = np.asarray(model.jac(x_true, u_arg(t)), dtype=float)
            e = x_hat - x_true
            e[2] = wrap_angle(e[2])
            e_unobs = e - np.linalg.pinv(Jt, rcond=1e-9) @ (Jt @ e)
            rec.append((t, x_true.copy(), x_hat.copy(), y.copy(), float(np.linalg.norm(e_unobs))))
        if step == steps:
            break
        # differentiator (Khalil): z_i' = z_{i+1} + alpha_i / eps^i (y - z_0)
        innov_y = wrap_angle(y - zhat[0])
        dz = np.empty_like(zhat)
        dz[:-1] = zhat[1:] + (alpha[:-1] / eps_pow[:-1])[:, None] * innov_y[None, :]
        dz[-1] = alpha[-1] / eps_pow[-1] * innov_y
        # observer: prediction + J^+ Gamma (Z_hat - Phi(x_hat))
        ua = u_arg(t)
        dx = np.asarray(model.drift(x_hat, ua), dtype=float).ravel()
        if t >= config.warmup_s:
            phi = np.asarray(model.phi(x_hat, ua), dtype=float).ravel()
            Jh = np.asarray(model.jac(x_hat, ua), dtype=float)
            innov = zhat.ravel() - phi
            innov[:p] = wrap_angle(innov[:p])
            dx = dx + np.linalg.pinv(Jh, rcond=config.pinv_rcond) @ (gamma * innov)
        if not np.all(np.isfinite(dx)):
            raise ConfigError("the observer diverged (non-finite estimate); lower gain_per_s or raise epsilon_s")
        zhat = zhat + dt * dz
        x_hat = x_hat + dt * dx
        # the vehicle: xi' = G(theta) (u + d) (eq. 1.7-1.8)
        w = _true_inputs(kind, t, 0)[0]
        v_f, v_h, om = (w[0], 0.0, w[1]) if kind is VehicleKind.UNICYCLE else tuple(w)
        c, s = math.cos(pose[2]), math.sin(pose[2])
        pose = pose + dt * np.array([c * v_f - s * v_h, s * v_f + c * v_h, om])

    t_arr = np.array([r_[0] for r_ in rec])
    return Simulation(
        t=t_arr,
        state_names=names,
        truth=np.array([r_[1] for r_ in rec]),
        estimate=np.array([r_[2] for r_ in rec]),
        bearings=np.array([r_[3] for r_ in rec]),
        unobservable_error=np.array([r_[4] for r_ in rec]),
        landmarks=landmarks,
        meta={
            "vehicle": kind.value,
            "markers": markers,
            "targets": targets,
            "half_markers": half_markers,
            "inputs": inputs.value,
            "order": k if inputs is InputKind.UNKNOWN else None,
            "channels": channels,
            "state_dimension": n,
            "seed": config.seed,
        },
    )


def plot_simulation(sim: Simulation, path: str | Path) -> Path:
    """Write a PNG of the estimation errors of ``sim`` to ``path``; returns the path."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    path = Path(path)
    fig = Figure(figsize=(8, 6.5), dpi=100)
    FigureCanvasAgg(fig)
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    floor = 1e-6
    ax1.semilogy(sim.t, np.maximum(sim.relative_error(), floor), color="k", lw=2, label="all states")
    for g, col in (("pose", "tab:blue"), ("landmarks", "tab:green"), ("inputs", "tab:orange")):
        if len(sim.group(g)):
            ax1.semilogy(sim.t, np.maximum(sim.relative_error(g), floor), color=col, lw=1, label=g)
    ax1.axhline(0.05, color="tab:red", ls="--", lw=1, label="5 % of initial")
    ax1.set_ylabel("|error| / |initial error|")
    m = sim.meta
    ax1.set_title(
        f"{m['vehicle']}, {m['markers']} marker(s), {m['half_markers']} half marker(s), {m['targets']} target(s), "
        f"{m['inputs']} inputs" + (f", k={m['order']}" if m.get("order") is not None else "")
    )
    ax1.legend(loc="lower left", fontsize=8)
    ax2.plot(sim.t, sim.rotation_error, color="tab:purple", label="rotation about landmark 1 [rad]")
    ax2.plot(sim.t, sim.unobservable_error, color="tab:gray", label="|error in ker J| (unobservable part)")
    ax2.axhline(0, color="k", lw=0.5)
    ax2.set_xlabel("time [s]")
    ax2.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, format="png")
    except OSError as e:
        raise DatasetError(f"cannot write {path}: {e.strerror or e}; choose a writable --out path") from None
    return path
