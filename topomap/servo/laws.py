"""Pose-regulation laws for appearance servoing (docs/theory.md section 3), as pure functions.

Every law takes the scaled pose of the vehicle in the goal frame, ``(x_s, z_s, theta) = (x/lambda,
z/lambda, theta)`` (docs/theory.md section 1 convention: ``x`` forward, ``z`` left, ``theta``
counter-clockwise), the configuration, the integral state and the control period, and returns a
:class:`~topomap.motion.Command` and the new integral state. Nothing is stored between calls.

The gains assume ``lambda = cfg.nominal_scale_m``; when it is off, the unknown scale only multiplies
the loop gains (docs/theory.md section 3). ``cfg.compensate=False`` gives the nominal laws: the
disturbance estimate ``d_omega_hat`` is ignored and there is no integral action.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from topomap.config import ServoConfig, UnicycleLaw
from topomap.motion import Command, saturate, wrap_angle

__all__ = [
    "LawState",
    "aicardi_coordinates",
    "along_track_error",
    "aicardi_command",
    "unicycle_law",
    "omni_law",
]


@dataclass(frozen=True)
class LawState:
    """Integral states carried from one control step to the next (the laws are pure).

    ``integral``: time integral of the scaled position error [lambda * s] — unicycle: (along-track
    error, 0); omnidirectional: (x, z) in the goal frame. ``aligning``: the unicycle is inside the
    docking radius and only aligns its heading (hysteresis between ``dock_radius_m`` and
    ``undock_radius_m``). ``reverse``: the unicycle is in front of the goal and backs into it.
    ``best_m, stall_s``: progress bookkeeping that lets the unicycle integrate when it stalls.
    """

    integral: tuple[float, float] = (0.0, 0.0)
    aligning: bool = False
    reverse: bool | None = None  # unicycle approaching backwards (None: not decided yet)
    best_m: float = math.inf  # unicycle: smallest estimated distance so far [m] ...
    stall_s: float = 0.0  # ... and the time since it last improved by stall_progress_m [s]


def aicardi_coordinates(x_s: float, z_s: float, theta: float) -> tuple[float, float, float]:
    """Aicardi's ``(e, alpha, theta_A)`` from the scaled pose (docs/theory.md section 1, eq. 1.9).

    ``e = rho``, ``alpha = beta = phi - theta + pi`` (bearing of the goal from the vehicle) and
    ``theta_A = phi + pi`` (direction of the goal from the vehicle, in the goal frame), both wrapped.
    docs/theory.md pairs theta_A with phi; the shift by pi makes the law arrive driving forward along the
    goal heading (with theta_A = phi it would arrive facing backwards). ``theta_A`` has the same
    dynamics as ``phi``, so the Lyapunov argument is unchanged.
    """
    e = math.hypot(x_s, z_s)
    phi = math.atan2(z_s, x_s)
    return e, wrap_angle(phi - theta + math.pi), wrap_angle(phi + math.pi)


def along_track_error(x_s: float, z_s: float, theta: float) -> float:
    """Signed distance to the goal along the vehicle's heading, ``e cos(alpha)`` [lambda]; > 0 ahead."""
    return -(math.cos(theta) * x_s + math.sin(theta) * z_s)


def aicardi_command(
    e_s: float,
    alpha: float,
    theta_a: float,
    cfg: ServoConfig,
    *,
    d_omega_hat: float = 0.0,
    kappa_hat: float | None = None,
    mu_hat: float = 0.0,
    v_extra: float = 0.0,
) -> Command:
    """Aicardi 1995 pose regulation, docs/theory.md section 3.

    ``v = gamma cos(alpha) e``, ``omega = k alpha + r (sin(alpha)/alpha)(alpha + h theta_A) - d_omega_hat``
    where ``r`` is the effective forward speed over the distance. Nominal law (``kappa_hat=None``):
    ``r = gamma cos(alpha)``, exact when ``lambda = lambda_0`` and nothing disturbs the forward
    channel. Scale-free variant: ``r = (kappa_hat v + mu_hat) / e_s`` — the ratio the observer sees
    (``kappa_hat`` scaled speed per commanded m/s, ``mu_hat`` scaled forward drift), so that
    ``V2 = (alpha^2 + h theta_A^2)/2`` has ``V2' = -k alpha^2`` for any scale and whatever ``v`` is
    (including the integral action ``v_extra`` added to ``v``). Saturation scales ``v`` and the
    nominal ``omega`` by one factor (the path's curvature and the sign of ``V'`` are kept) while
    ``d_omega_hat`` keeps its share of the turn-rate budget.
    """
    lam0 = cfg.nominal_scale_m
    d_hat = d_omega_hat if cfg.compensate else 0.0
    v_nom = cfg.gamma * lam0 * math.cos(alpha) * e_s
    v_room = max(1e-6, cfg.max_speed_mps - abs(v_extra))
    v = v_nom * min(1.0, v_room / max(abs(v_nom), 1e-12))
    sinc = math.sin(alpha) / alpha if abs(alpha) > 1e-9 else 1.0
    w_room = max(1e-6, cfg.max_turn_rps - min(abs(d_hat), 0.5 * cfg.max_turn_rps))
    if kappa_hat is None:
        omega = cfg.k_alpha * alpha + (v / (lam0 * max(e_s, 1e-12))) * sinc * (alpha + cfg.h * theta_a)
        sigma = min(1.0, w_room / max(abs(omega), 1e-12))
        return Command(sigma * v + v_extra, 0.0, sigma * omega - d_hat).clipped(cfg.max_speed_mps, cfg.max_turn_rps)
    v = v + v_extra
    ratio = (kappa_hat * v + (mu_hat if cfg.compensate else 0.0)) / max(e_s, 1e-12)
    omega = cfg.k_alpha * alpha + ratio * sinc * (alpha + cfg.h * theta_a)
    sigma = min(1.0, w_room / max(abs(omega), 1e-12))
    return Command(sigma * v, 0.0, sigma * omega - d_hat).clipped(cfg.max_speed_mps, cfg.max_turn_rps)


def _integrate(value: float, err: float, dt: float, gain: float, limit_mps: float, lam0: float) -> float:
    """Conditional integration with clamping: ``|gain * lambda_0 * integral| <= limit``."""
    if gain <= 0:
        return 0.0
    bound = limit_mps / (gain * lam0)
    return saturate(value + err * dt, bound)


def unicycle_law(
    x_s: float,
    z_s: float,
    theta: float,
    cfg: ServoConfig,
    state: LawState = LawState(),
    dt: float = 0.1,
    *,
    d_omega_hat: float = 0.0,
    kappa_hat: float | None = None,
    mu_hat: float = 0.0,
) -> tuple[Command, LawState]:
    """Unicycle regulation to the goal pose: Aicardi far away, heading alignment at the goal.

    Away from the goal: :func:`aicardi_command` (``cfg.unicycle_law``: ``aicardi`` nominal, or
    ``scale_free`` with ``kappa_hat, mu_hat`` from the observer). A vehicle in front of the goal (``x > 0``) backs into it:
    the same law applied to the reversed vehicle, whose pose in the reversed goal frame is
    ``(-x, -z, theta)``, with ``v`` negated — otherwise an overshoot would make Aicardi turn around
    (``alpha = pi``). The side is chosen with hysteresis during the approach, and afresh on every
    step spent aligning: a vehicle that overshoots while aligning leaves alignment backing up. Inside ``dock_radius_m`` (estimated, ``lambda_0 rho_s``) the bearing of the goal
    is undefined at the scale of the measurement noise, so the vehicle aligns its heading:
    ``omega = -k_theta theta - d_omega_hat`` while ``v = k_p eps`` regulates the along-track error.
    Integral action on ``eps`` (``compensate``) learns the forward disturbance (docs/theory.md section 3:
    "needs integral or adaptive action"). It runs while aligning, and within ``integral_zone_m``
    when the distance has not improved by ``stall_progress_m`` for ``stall_time_s`` (the vehicle is
    held off by a forward disturbance); otherwise it is held (and still applied): conditional
    integration, so it does not wind up during the approach.
    """
    lam0 = cfg.nominal_scale_m
    band = cfg.undock_radius_m
    reverse = state.reverse
    if reverse is None or state.aligning:  # leaving alignment past the goal backs into it, not turns around
        reverse = x_s > 0
    elif reverse and lam0 * x_s < -band:
        reverse = False
    elif not reverse and lam0 * x_s > band:
        reverse = True
    dist_m = lam0 * math.hypot(x_s, z_s)
    aligning = dist_m < (cfg.undock_radius_m if state.aligning else cfg.dock_radius_m)
    eps = along_track_error(x_s, z_s, theta)
    ki = cfg.k_i if cfg.compensate else 0.0
    integ = state.integral[0]
    best_m, stall_s = state.best_m, state.stall_s
    if dist_m < best_m - cfg.stall_progress_m:
        best_m, stall_s = dist_m, 0.0
    else:
        stall_s += dt
    if aligning or (stall_s > cfg.stall_time_s and dist_m < cfg.integral_zone_m):
        integ = _integrate(integ, eps, dt, ki, cfg.integral_limit_mps, lam0)
    v_i = ki * lam0 * integ
    if aligning:
        d_hat = d_omega_hat if cfg.compensate else 0.0
        v = saturate(cfg.k_p * lam0 * eps, max(0.0, cfg.max_speed_mps - abs(v_i))) + v_i
        cmd = Command(v, 0.0, -cfg.k_theta * wrap_angle(theta) - d_hat).clipped(cfg.max_speed_mps, cfg.max_turn_rps)
    else:
        sgn = -1.0 if reverse else 1.0
        e_s, alpha, theta_a = aicardi_coordinates(sgn * x_s, sgn * z_s, theta)
        kap = kappa_hat if cfg.unicycle_law is UnicycleLaw.SCALE_FREE else None
        c = aicardi_command(
            e_s, alpha, theta_a, cfg, d_omega_hat=d_omega_hat, kappa_hat=kap, mu_hat=sgn * mu_hat, v_extra=sgn * v_i
        )
        cmd = Command(sgn * c.v_f, 0.0, c.omega)
    return cmd, LawState((integ, 0.0), aligning, reverse, best_m, stall_s)


def omni_law(
    x_s: float,
    z_s: float,
    theta: float,
    cfg: ServoConfig,
    state: LawState = LawState(),
    dt: float = 0.1,
    *,
    d_omega_hat: float = 0.0,
) -> tuple[Command, LawState]:
    """Omnidirectional proportional-integral regulation, docs/theory.md section 3.

    ``u_lin = -R(theta)^T lambda_0 (k_p p_s + k_i integral(p_s))``, ``omega = -k_theta theta - d_omega_hat``;
    closed loop ``p' = -(lambda_0/lambda) (k_p p + k_i integral(p)) + R d_lin``: the scale is a positive
    gain and the integral rejects a constant linear disturbance. The linear command is saturated as a
    vector (its direction is kept).
    """
    lam0 = cfg.nominal_scale_m
    ki = cfg.k_i if cfg.compensate else 0.0
    d_hat = d_omega_hat if cfg.compensate else 0.0
    ix, iz = state.integral
    if lam0 * math.hypot(x_s, z_s) < cfg.integral_zone_m:
        ix = _integrate(ix, x_s, dt, ki, cfg.integral_limit_mps, lam0)
        iz = _integrate(iz, z_s, dt, ki, cfg.integral_limit_mps, lam0)
    wx = -lam0 * (cfg.k_p * x_s + ki * ix)  # desired velocity in the goal frame [m/s]
    wz = -lam0 * (cfg.k_p * z_s + ki * iz)
    c, s = math.cos(theta), math.sin(theta)
    v_f, v_h = c * wx + s * wz, -s * wx + c * wz  # R(theta)^T w
    m = max(abs(v_f), abs(v_h))
    if m > cfg.max_speed_mps:
        v_f, v_h = v_f * cfg.max_speed_mps / m, v_h * cfg.max_speed_mps / m
    omega = -cfg.k_theta * wrap_angle(theta) - d_hat
    return Command(v_f, v_h, saturate(omega, cfg.max_turn_rps)), LawState((ix, iz), False)
