"""Control laws (topomap.servo.laws): conventions, Lyapunov property, saturation, and closed-loop
behaviour on the kinematic models xi' = G(theta)(u + d) (docs/theory.md sections 1, 3), integrated exactly,
from a grid of initial poses, for every disturbance preset and several unknown scales lambda."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
from servo_synth import DISTURBANCES, disturbance, drive

from topomap.config import ServoConfig, servo_preset
from topomap.motion import Command
from topomap.servo.laws import (
    LawState,
    aicardi_command,
    aicardi_coordinates,
    along_track_error,
    omni_law,
    unicycle_law,
)
from topomap.servo.disturbance import DisturbanceObserver

CFG = servo_preset("default")
LAM0 = CFG.nominal_scale_m
# Initial poses in the goal frame (x forward, z left, theta): behind, beside, in front, turned away.
STARTS = [(-2.0, 0.6, 0.4), (-0.6, -1.2, -1.0), (1.0, 0.5, 0.0), (-0.3, 0.3, 2.5)]
SCALES = [0.5, 1.0, 2.0]  # true lambda / nominal lambda_0


def wrap(a):
    return (a + math.pi) % (2 * math.pi) - math.pi


def episode(cfg: ServoConfig, vehicle: str, start, dist_name: str, lam: float, *, t_max=40.0, dt=0.1, seed=0):
    """Closed loop on the scaled pose (what the geometry measures) with measurement noise; returns the
    true final pose (x, z, theta) in the goal frame."""
    rng = np.random.default_rng(seed)
    dist = disturbance(dist_name, seed)
    obs = DisturbanceObserver(cfg.observer, 1.0 / cfg.nominal_scale_m)
    pose, state, last, t = start, LawState(), None, 0.0
    while t < t_max:
        th = wrap(pose[2] + rng.normal(0, 0.001))
        p = np.array(pose[:2]) / lam + rng.normal(0, 0.002, 2)
        est = obs.update(dt, last, th, p)
        if vehicle == "unicycle":
            cmd, state = unicycle_law(p[0], p[1], th, cfg, state, dt, d_omega_hat=est.d_omega,
                                      kappa_hat=est.kappa, mu_hat=est.mu_f)
        else:
            cmd, state = omni_law(p[0], p[1], th, cfg, state, dt, d_omega_hat=est.d_omega)
        pose = drive(pose, cmd.as_tuple(), dist, t, dt, vehicle == "unicycle", substeps=2)
        last, t = cmd, t + dt
    return pose


@functools.lru_cache(maxsize=None)
def grid(preset: str, vehicle: str, dist_name: str, scale: float):
    """Final (position error [m], heading error [deg]) for every start."""
    cfg = servo_preset(preset)
    out = []
    for k, s in enumerate(STARTS):
        x, z, th = episode(cfg, vehicle, s, dist_name, scale * cfg.nominal_scale_m, seed=k)
        out.append((math.hypot(x, z), abs(math.degrees(wrap(th)))))
    return np.array(out)


# ---------------------------------------------------------------------------- conventions
def test_aicardi_coordinates_behind_and_facing_the_goal_are_zero():
    e, alpha, theta_a = aicardi_coordinates(-2.0, 0.0, 0.0)
    assert (e, alpha, theta_a) == pytest.approx((2.0, 0.0, 0.0), abs=1e-12)
    # a vehicle behind and to the right of the goal (z < 0) sees it ahead-left: alpha > 0 (CCW)
    _, alpha, _ = aicardi_coordinates(-1.0, -1.0, 0.0)
    assert alpha == pytest.approx(math.pi / 4)


def test_along_track_error_is_the_goal_distance_ahead():
    assert along_track_error(-1.5, 0.0, 0.0) == pytest.approx(1.5)
    assert along_track_error(0.0, 1.0, math.pi / 2) == pytest.approx(-1.0)


def test_scale_free_law_makes_v2_decrease_at_minus_k_alpha_squared():
    # docs/theory.md section 3: omega = k a + r (sin a / a)(a + h thA) - d_hat gives V2' = -k a^2 for any
    # scale and forward disturbance, when r is the true (v + d_v) / e.
    rng = np.random.default_rng(0)
    cfg = ServoConfig(max_speed_mps=100.0, max_turn_rps=100.0)
    for _ in range(50):
        e_s, alpha, theta_a = rng.uniform(0.2, 2.0), rng.uniform(-3, 3), rng.uniform(-3, 3)
        lam, d_f, d_w = rng.uniform(0.3, 3.0), rng.uniform(-0.05, 0.05), rng.uniform(-0.2, 0.2)
        kappa, mu = 1.0 / lam, d_f / lam
        cmd = aicardi_command(e_s, alpha, theta_a, cfg, d_omega_hat=d_w, kappa_hat=kappa, mu_hat=mu)
        e = lam * e_s
        v_eff, w_eff = cmd.v_f + d_f, cmd.omega + d_w
        alpha_dot = math.sin(alpha) * v_eff / e - w_eff  # docs/theory.md section 1, unicycle
        theta_a_dot = math.sin(alpha) * v_eff / e
        v2_dot = alpha * alpha_dot + cfg.h * theta_a * theta_a_dot
        assert v2_dot == pytest.approx(-cfg.k_alpha * alpha**2, rel=1e-9, abs=1e-12)


def test_nominal_aicardi_lyapunov_derivative_is_negative_at_the_nominal_scale():
    rng = np.random.default_rng(1)
    cfg = ServoConfig(unicycle_law="aicardi", max_speed_mps=100.0, max_turn_rps=100.0)
    for _ in range(50):
        e_s, alpha, theta_a = rng.uniform(0.2, 2.0), rng.uniform(-3, 3), rng.uniform(-3, 3)
        cmd = aicardi_command(e_s, alpha, theta_a, cfg)
        e = LAM0 * e_s
        e_dot = -math.cos(alpha) * cmd.v_f
        alpha_dot = math.sin(alpha) * cmd.v_f / e - cmd.omega
        theta_a_dot = math.sin(alpha) * cmd.v_f / e
        v_dot = (e * e_dot) + alpha * alpha_dot + cfg.h * theta_a * theta_a_dot
        assert v_dot == pytest.approx(-cfg.gamma * math.cos(alpha) ** 2 * e**2 - cfg.k_alpha * alpha**2, rel=1e-9, abs=1e-12)


def test_commands_respect_the_saturations():
    rng = np.random.default_rng(2)
    for _ in range(200):
        x, z, th = rng.uniform(-20, 20), rng.uniform(-20, 20), rng.uniform(-3.1, 3.1)
        for law in (unicycle_law, omni_law):
            cmd, _ = law(x, z, th, CFG, LawState(), 0.1, d_omega_hat=rng.uniform(-0.3, 0.3))
            assert abs(cmd.v_f) <= CFG.max_speed_mps + 1e-12
            assert abs(cmd.v_h) <= CFG.max_speed_mps + 1e-12
            assert abs(cmd.omega) <= CFG.max_turn_rps + 1e-12
        cmd, _ = unicycle_law(x, z, th, CFG, LawState(), 0.1)
        assert cmd.v_h == 0.0


def test_uncompensated_law_ignores_the_disturbance_estimate_and_integrates_nothing():
    cfg = servo_preset("uncompensated")
    a, sa = omni_law(0.01, 0.02, 0.1, cfg, LawState(), 0.1, d_omega_hat=0.2)
    b, sb = omni_law(0.01, 0.02, 0.1, cfg, LawState(), 0.1, d_omega_hat=0.0)
    assert a == b and sa.integral == (0.0, 0.0)
    c, _ = omni_law(0.01, 0.02, 0.1, CFG, LawState(), 0.1, d_omega_hat=0.2)
    assert c.omega == pytest.approx(b.omega - 0.2)


def test_laws_are_pure():
    state = LawState(integral=(0.01, 0.0), aligning=True, reverse=False)
    first = unicycle_law(0.01, 0.005, 0.02, CFG, state, 0.1, d_omega_hat=0.1)
    again = unicycle_law(0.01, 0.005, 0.02, CFG, state, 0.1, d_omega_hat=0.1)
    assert first == again and state == LawState(integral=(0.01, 0.0), aligning=True, reverse=False)


@pytest.mark.parametrize("x_m, z_m", [(0.2, 0.2), (0.24, 0.1)])
def test_a_unicycle_that_overshoots_while_aligning_backs_up_instead_of_turning_around(x_m, z_m):
    # past the goal, beyond the undock radius but inside the approach's reverse band: with that
    # hysteresis alone the law drove forward and turned around (alpha = pi), losing the goal's view
    lam0 = CFG.nominal_scale_m
    assert math.hypot(x_m, z_m) > CFG.undock_radius_m > x_m
    x, z, th, state, widest = x_m, z_m, 0.0, LawState(aligning=True, reverse=False), 0.0
    for _ in range(100):  # kinematic unicycle in the goal frame, heading (cos th, sin th)
        cmd, state = unicycle_law(x / lam0, z / lam0, th, CFG, state, 0.1)
        x, z, th = x + 0.1 * cmd.v_f * math.cos(th), z + 0.1 * cmd.v_f * math.sin(th), th + 0.1 * cmd.omega
        widest = max(widest, abs(th))
    assert math.degrees(widest) < 90.0
    assert math.hypot(x, z) < 0.05


def test_integral_state_is_passed_in_and_returned():
    state = LawState()
    for _ in range(10):
        _, state = omni_law(0.01, -0.01, 0.0, CFG, state, 0.1)
    assert state.integral == pytest.approx((0.1 * 10 * 0.01, -0.1 * 10 * 0.01))


# ---------------------------------------------------------------------------- closed loop
@pytest.mark.slow
@pytest.mark.parametrize("vehicle", ["unicycle", "omni"])
@pytest.mark.parametrize("dist_name", sorted(DISTURBANCES))
def test_closed_loop_converges_from_a_grid_of_poses(vehicle, dist_name):
    for scale in SCALES:
        res = grid("default", vehicle, dist_name, scale)
        # the unknown scale stretches the estimated distances, hence the residual, by lambda / lambda_0
        tol_m = 0.06 * max(1.0, scale)
        assert res[:, 0].max() < tol_m * (1.75 if dist_name in ("sinusoidal", "walk", "harsh") else 1.0), (scale, res)
        assert np.median(res[:, 0]) < tol_m, (scale, res)
        assert res[:, 1].max() < 3.0, (scale, res)


@pytest.mark.slow
@pytest.mark.parametrize("vehicle", ["unicycle", "omni"])
def test_compensation_removes_the_heading_error_of_a_constant_d_omega(vehicle):
    # docs/theory.md section 3: the nominal law keeps a steady heading error under a constant d_omega
    for scale in SCALES:
        comp = grid("default", vehicle, "omega", scale)
        nominal = grid("uncompensated", vehicle, "omega", scale)
        assert np.median(nominal[:, 1]) > 5.0  # d_omega / k_theta = 8.6 deg
        assert np.median(comp[:, 1]) * 3 < np.median(nominal[:, 1])
        assert np.median(comp[:, 0]) < 0.06 * max(1.0, scale)


@pytest.mark.slow
@pytest.mark.parametrize("vehicle", ["unicycle", "omni"])
@pytest.mark.parametrize("dist_name", ["bias", "harsh"])
def test_compensated_law_ends_at_least_three_times_closer(vehicle, dist_name):
    # the goal (>= 3x smaller median error than the uncompensated servo), at law level
    for scale in SCALES:
        comp = np.median(grid("default", vehicle, dist_name, scale)[:, 0])
        nominal = np.median(grid("uncompensated", vehicle, dist_name, scale)[:, 0])
        assert comp * 3 < nominal, (scale, comp, nominal)


@pytest.mark.slow
def test_nominal_aicardi_law_also_converges_without_disturbance():
    for scale in (0.5, 1.0, 2.0):
        res = grid("aicardi", "unicycle", "none", scale)
        assert res[:, 0].max() < 0.06 * max(1.0, scale) and res[:, 1].max() < 3.0, res


def test_command_type():
    cmd, state = unicycle_law(-1.0, 0.0, 0.0, CFG)
    assert isinstance(cmd, Command) and isinstance(state, LawState)
    assert cmd.v_f > 0 and abs(cmd.omega) < 1e-9  # straight ahead
