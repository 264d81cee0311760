"""Vehicle kinematics with unknown input disturbances, integrated exactly, and wall collisions.

docs/theory.md section 1, eq. 1.7-1.8: ``xi' = G(theta) (u + d)`` with ``xi = (x, z, theta)``,
``u = (v_f, v_h, omega)`` the command, ``d = (d_f, d_h, d_omega)`` the unknown disturbance and
``G(theta) = [[cos, -sin, 0], [sin, cos, 0], [0, 0, 1]]``. A unicycle has ``v_h = d_h = 0``.

Inputs are held constant over a fixed step (``VehicleConfig.step_s``); for constant inputs the
motion is an arc that :func:`arc_step` integrates in closed form, so the only approximation is the
sampling of a time-varying disturbance (evaluated at the middle of each step).

Disturbances (:class:`DisturbanceConfig`) are the sum of a constant bias, sinusoids, a slip (a
fraction of each commanded velocity lost, ``d = -slip * u``) and a random walk (an Ornstein-Uhlenbeck
process: a random walk pulled slowly back to zero, so it wanders but stays drivable). Presets live
in :data:`DISTURBANCE_PRESETS`; :func:`parse_disturbance` also reads custom values
(``"bias,bias_omega_rps=0.2"``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from topomap.config import preset_with_overrides
from topomap.errors import ConfigError, choose
from topomap.motion import Command, VehicleKind, vehicle_kind

__all__ = [
    "DisturbanceConfig",
    "DISTURBANCE_PRESETS",
    "disturbance_preset",
    "parse_disturbance",
    "Disturbance",
    "VehicleConfig",
    "arc_step",
    "Vehicle",
]


@dataclass(frozen=True)
class DisturbanceConfig:
    """Unknown input disturbance ``d = bias + sinusoid - slip * u + random walk`` per channel.

    Channels: ``f`` forward [m/s], ``h`` sideways (left) [m/s], ``omega`` turning [rad/s].
    The sinusoids have period ``sin_period_s`` and phases 0, pi/2, pi/4 on the three channels.
    ``slip_*`` is the fraction of each commanded velocity that the vehicle loses (0.15 = 15 %).
    ``noise_*`` is the standard deviation the random walk settles at, ``noise_tau_s`` its correlation time.
    """

    bias_f_mps: float = 0.0
    bias_h_mps: float = 0.0
    bias_omega_rps: float = 0.0
    sin_f_mps: float = 0.0
    sin_h_mps: float = 0.0
    sin_omega_rps: float = 0.0
    sin_period_s: float = 8.0
    slip_f: float = 0.0
    slip_h: float = 0.0
    slip_omega: float = 0.0
    noise_f_mps: float = 0.0
    noise_h_mps: float = 0.0
    noise_omega_rps: float = 0.0
    noise_tau_s: float = 10.0

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ConfigError(f"disturbance {f.name}={v!r} must be a finite number")
            object.__setattr__(self, f.name, float(v))
        if self.sin_period_s <= 0 or self.noise_tau_s <= 0:
            raise ConfigError("disturbance sin_period_s and noise_tau_s must be positive")
        for name in ("slip_f", "slip_h", "slip_omega"):
            if not -1.0 < getattr(self, name) < 1.0:
                raise ConfigError(f"disturbance {name}={getattr(self, name)} must lie in (-1, 1) (a fraction of the command)")
        for name in ("noise_f_mps", "noise_h_mps", "noise_omega_rps"):
            if getattr(self, name) < 0:
                raise ConfigError(f"disturbance {name} must not be negative")

    @property
    def bias(self) -> np.ndarray:
        return np.array([self.bias_f_mps, self.bias_h_mps, self.bias_omega_rps])

    @property
    def sin_amplitude(self) -> np.ndarray:
        return np.array([self.sin_f_mps, self.sin_h_mps, self.sin_omega_rps])

    @property
    def slip(self) -> np.ndarray:
        return np.array([self.slip_f, self.slip_h, self.slip_omega])

    @property
    def noise_std(self) -> np.ndarray:
        return np.array([self.noise_f_mps, self.noise_h_mps, self.noise_omega_rps])

    @property
    def is_zero(self) -> bool:
        return not (self.bias.any() or self.sin_amplitude.any() or self.slip.any() or self.noise_std.any())


#: Phases of the sinusoidal disturbance on the (f, h, omega) channels [rad].
SIN_PHASES = np.array([0.0, math.pi / 2, math.pi / 4])

_BIAS = dict(bias_f_mps=0.04, bias_h_mps=0.03, bias_omega_rps=0.15)
_SIN = dict(sin_f_mps=0.05, sin_h_mps=0.04, sin_omega_rps=0.2, sin_period_s=8.0)
_SLIP = dict(slip_f=0.15, slip_h=0.15, slip_omega=0.1)
_NOISE = dict(noise_f_mps=0.03, noise_h_mps=0.02, noise_omega_rps=0.1, noise_tau_s=10.0)

#: Named disturbances. Sized for nominal speeds of ~0.3 m/s and ~0.5 rad/s: large enough that an
#: uncompensated servo drifts visibly, small enough to stay drivable.
DISTURBANCE_PRESETS: dict[str, DisturbanceConfig] = {
    "none": DisturbanceConfig(),
    "bias": DisturbanceConfig(**_BIAS),  # constant: 4 cm/s forward, 3 cm/s sideways, 0.15 rad/s turning
    "sinusoidal": DisturbanceConfig(**_SIN),  # 8 s period: 5 cm/s, 4 cm/s, 0.2 rad/s amplitudes
    "slip": DisturbanceConfig(**_SLIP),  # 15 % of the commanded speeds and 10 % of the turn rate lost
    "noisy": DisturbanceConfig(**_NOISE),  # random walk settling at 3 cm/s, 2 cm/s, 0.1 rad/s std
    "harsh": DisturbanceConfig(  # all of them at once
        **_BIAS, **_SLIP,
        sin_f_mps=0.03, sin_h_mps=0.02, sin_omega_rps=0.1, sin_period_s=8.0,
        noise_f_mps=0.02, noise_h_mps=0.015, noise_omega_rps=0.05, noise_tau_s=10.0,
    ),
}


def disturbance_preset(name: str) -> DisturbanceConfig:
    """The named preset; an unknown name lists the valid ones."""
    return choose(DISTURBANCE_PRESETS, name, "disturbance preset")


def parse_disturbance(spec: str | DisturbanceConfig | None) -> DisturbanceConfig:
    """A disturbance from ``"PRESET"``, ``"key=value,..."`` or ``"PRESET,key=value,..."``.

    Keys are the fields of :class:`DisturbanceConfig` (``bias_omega_rps=0.2,slip_f=0.1``); they
    override the preset (``none`` when no preset is named).
    """
    if spec is None:
        return DISTURBANCE_PRESETS["none"]
    if isinstance(spec, DisturbanceConfig):
        return spec
    base, items = preset_with_overrides(spec, "disturbance", DISTURBANCE_PRESETS,
                                        (f.name for f in dataclasses.fields(DisturbanceConfig)))
    if not items:
        return base
    values = {}
    for key, val in items:
        try:
            values[key] = float(val)
        except ValueError:
            raise ConfigError(f"disturbance {key}={val!r} is not a number") from None
    return dataclasses.replace(base, **values)


class Disturbance:
    """The realised disturbance process of one vehicle (seeded random walk)."""

    def __init__(self, config: DisturbanceConfig, kind: VehicleKind, seed: int = 0) -> None:
        self.config = config
        self.kind = kind
        self._rng = np.random.default_rng([int(seed), 11])
        self._walk = np.zeros(3)
        self._mask = np.array([1.0, 0.0, 1.0]) if kind is VehicleKind.UNICYCLE else np.ones(3)

    def sample(self, t_mid: float, u: np.ndarray, h: float) -> np.ndarray:
        """``d`` (3,) [m/s, m/s, rad/s] held over the step ``[t_mid - h/2, t_mid + h/2]`` under command ``u`` (3,).

        Advances the random walk by ``h`` (exact Ornstein-Uhlenbeck update).
        """
        c = self.config
        std = c.noise_std
        if std.any():
            a = math.exp(-h / c.noise_tau_s)
            self._walk = a * self._walk + std * math.sqrt(1.0 - a * a) * self._rng.standard_normal(3)
        d = c.bias + c.sin_amplitude * np.sin(2.0 * math.pi * t_mid / c.sin_period_s + SIN_PHASES) - c.slip * u + self._walk
        return d * self._mask


@dataclass(frozen=True)
class VehicleConfig:
    """Body and limits of the simulated vehicle."""

    kind: VehicleKind = VehicleKind.UNICYCLE
    radius_m: float = 0.2  # collision disc around the camera centre [m]
    max_speed_mps: float = 1.0  # commands are saturated to this (each linear channel) [m/s]
    max_turn_rps: float = 2.0  # ... and this [rad/s]
    step_s: float = 0.01  # fixed integration step [s]

    def __post_init__(self) -> None:
        object.__setattr__(self, "kind", vehicle_kind(self.kind))
        if not 0.0 < self.radius_m < 1.0:
            raise ConfigError(f"vehicle radius {self.radius_m} m must lie in (0, 1)")
        if self.max_speed_mps <= 0 or self.max_turn_rps <= 0:
            raise ConfigError("vehicle speed limits must be positive")
        if not 1e-4 <= self.step_s <= 0.1:
            raise ConfigError(f"integration step {self.step_s} s must lie in [1e-4, 0.1]")


def arc_step(pose: np.ndarray, v: np.ndarray, h: float) -> np.ndarray:
    """Exact solution of ``xi' = G(theta) v`` over ``h`` seconds for a constant body velocity ``v`` (3,).

    docs/theory.md eq. 1.7: with ``w = v[2]`` the heading turns by ``w h`` and the displacement is
    ``R(theta) [[S, -C], [C, S]] (v_f, v_h)`` with ``S = sin(w h)/w``, ``C = (1 - cos(w h))/w``
    (written with ``np.sinc`` so that ``w -> 0`` is exact too).
    """
    x, z, theta = pose
    v_f, v_h, omega = v
    a = omega * h
    S = h * np.sinc(a / math.pi)  # sin(a)/omega
    C = h * math.sin(a / 2.0) * np.sinc(a / (2.0 * math.pi))  # (1 - cos a)/omega
    bx = S * v_f - C * v_h  # displacement in the frame of the initial heading
    bz = C * v_f + S * v_h
    c, s = math.cos(theta), math.sin(theta)
    return np.array([x + c * bx - s * bz, z + s * bx + c * bz, theta + a])


class Vehicle:
    """Pose, clock and disturbance of one simulated vehicle among ``segments`` (S, 4) walls.

    The pose is ground truth: only :class:`topomap.sim.simulator.GroundTruth` hands it out.
    """

    def __init__(
        self,
        config: VehicleConfig,
        disturbance: DisturbanceConfig,
        segments: np.ndarray,
        pose: tuple[float, float, float],
        seed: int = 0,
    ) -> None:
        from topomap.sim.world import segment_distances

        self.config = config
        self.disturbance = Disturbance(disturbance, config.kind, seed)
        self._segments = np.asarray(segments, dtype=float)
        self._dist = segment_distances
        self.pose = np.array(pose, dtype=float)
        self.time_s = 0.0
        self.last_d = np.zeros(3)
        self.collisions = 0
        self._anchor: np.ndarray | None = None
        self._local = self._segments
        # Per integration step: start time, length, commanded u (3), disturbance d (3).
        self.log: list[tuple[float, ...]] = []

    def clearance(self, xz=None) -> float:
        """Distance [m] from the vehicle's centre (or the point ``xz``) to the nearest wall."""
        p = self.pose[:2] if xz is None else np.asarray(xz, dtype=float)
        if len(self._segments) == 0:
            return math.inf
        return float(self._dist(p[None, :], self._segments).min())

    _LOCAL_M = 0.5  # walls within radius + this of an anchor point are the only ones checked near it

    def _local_clearance(self, xz: np.ndarray) -> float:
        """Distance to the nearest wall, exact whenever it is below the radius (walls near an anchor)."""
        if self._anchor is None or np.hypot(*(xz - self._anchor)) > self._LOCAL_M / 2:
            self._anchor = np.array(xz, dtype=float)
            if len(self._segments):
                d = self._dist(self._anchor[None, :], self._segments)[0]
                self._local = self._segments[d <= self.config.radius_m + self._LOCAL_M]
            else:
                self._local = self._segments
        if len(self._local) == 0:
            return math.inf
        return float(self._dist(np.asarray(xz, dtype=float)[None, :], self._local).min())

    def _blocked(self, old_clear: float, new_xz: np.ndarray) -> tuple[bool, float]:
        new_clear = self._local_clearance(new_xz)
        return (new_clear < self.config.radius_m and new_clear < old_clear), new_clear

    def advance(self, command: Command, dt: float) -> tuple[bool, bool]:
        """Drive ``command`` for ``dt`` seconds; returns ``(collided, saturated)``.

        The vehicle stops translating where its disc would enter a wall (it keeps turning, which a
        disc can always do); a command beyond the limits is saturated.
        """
        cfg = self.config
        if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
            raise ConfigError(f"time step dt={dt!r} must be a positive number of seconds")
        cmd = command.for_vehicle(cfg.kind)
        clipped = cmd.clipped(cfg.max_speed_mps, cfg.max_turn_rps)
        saturated = clipped != cmd
        u = np.array(clipped.as_tuple())
        n = max(1, int(round(dt / cfg.step_s)))
        h = dt / n  # the fixed step, adjusted so that whole steps fill dt exactly
        collided = False
        blocked = False  # once blocked, translation stops for the rest of this command
        clear = self._local_clearance(self.pose[:2])
        for _ in range(n):
            d = self.disturbance.sample(self.time_s + h / 2.0, u, h)
            self.log.append((self.time_s, h, *u, *d))
            v = u + d
            if blocked:
                v = np.array([0.0, 0.0, v[2]])
            new = arc_step(self.pose, v, h)
            hit, new_clear = self._blocked(clear, new[:2])
            if hit:
                # Bisect the step for the last collision-free fraction of the arc.
                lo, hi = 0.0, 1.0
                for _ in range(30):
                    mid = (lo + hi) / 2.0
                    if self._blocked(clear, arc_step(self.pose, v, mid * h)[:2])[0]:
                        hi = mid
                    else:
                        lo = mid
                stop = arc_step(self.pose, v, lo * h)
                rest = arc_step(np.array([0.0, 0.0, stop[2]]), np.array([0.0, 0.0, v[2]]), (1.0 - lo) * h)
                new = np.array([stop[0], stop[1], rest[2]])
                new_clear = self._local_clearance(new[:2])
                collided = blocked = True
            self.pose = new
            clear = new_clear
            self.time_s += h
            self.last_d = d
        if collided:
            self.collisions += 1
        self.pose[2] = math.atan2(math.sin(self.pose[2]), math.cos(self.pose[2]))
        return collided, saturated
