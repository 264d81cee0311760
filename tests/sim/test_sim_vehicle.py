"""Kinematics (docs/theory.md eq. 1.7-1.8) against closed forms, disturbance presets, collisions."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from sim.sim_helpers import box_world

from topomap.errors import ConfigError
from topomap.motion import Command, VehicleKind
from topomap.sim.simulator import Simulator
from topomap.sim.vehicle import (
    DISTURBANCE_PRESETS,
    SIN_PHASES,
    Disturbance,
    DisturbanceConfig,
    VehicleConfig,
    arc_step,
    parse_disturbance,
)

BOX = box_world(100.0)
START = (1.0, -2.0, 0.3)


class _NoRenderer:
    """Kinematics tests need no images."""

    camera = None

    def render(self, pose):  # pragma: no cover - never called
        raise AssertionError

    def close(self):
        pass


def _sim(vehicle="unicycle", disturbance="none", seed=0, world=BOX, start=START):
    return Simulator(world, vehicle=vehicle, disturbance=disturbance, seed=seed, start_pose=start, renderer=_NoRenderer())


def closed_form(pose0, v_f, v_h, omega, t):
    """xi(t) for constant body velocities: straight line if omega == 0, else a circle (eq. 1.7)."""
    x0, z0, th0 = pose0
    if omega == 0.0:
        c, s = math.cos(th0), math.sin(th0)
        return np.array([x0 + (v_f * c - v_h * s) * t, z0 + (v_f * s + v_h * c) * t, th0])
    th = th0 + omega * t
    x = x0 + (v_f * (math.sin(th) - math.sin(th0)) + v_h * (math.cos(th) - math.cos(th0))) / omega
    z = z0 + (-v_f * (math.cos(th) - math.cos(th0)) + v_h * (math.sin(th) - math.sin(th0))) / omega
    return np.array([x, z, th])


def _same_pose(a, b, tol):
    assert abs(a[0] - b[0]) < tol and abs(a[1] - b[1]) < tol
    assert abs(math.atan2(math.sin(a[2] - b[2]), math.cos(a[2] - b[2]))) < tol


def _drive(sim, cmd, seconds, dt=0.1):
    for _ in range(int(round(seconds / dt))):
        rep = sim.robot.apply(cmd, dt)
        assert not rep.collided
    return np.array(sim.ground_truth.pose())


MOTIONS = {  # (vehicle, command)
    "line": ("unicycle", Command(0.3, 0.0, 0.0)),
    "circle": ("unicycle", Command(0.3, 0.0, 0.5)),
    "omni-line": ("omni", Command(0.3, 0.2, 0.0)),
    "omni-circle": ("omni", Command(0.3, -0.2, -0.4)),
}


def test_arc_step_matches_closed_form():
    for v in [(0.3, 0.0, 0.0), (0.3, 0.0, 0.5), (0.0, 0.4, -2.0), (0.2, -0.1, 3.0)]:
        _same_pose(arc_step(np.array(START), np.array(v), 3.7), closed_form(START, *v, 3.7), 1e-9)
    # A vanishing turn rate is still exact (no 0/0): it tends to the straight line.
    _same_pose(arc_step(np.array(START), np.array([0.2, -0.1, 1e-12]), 3.7), closed_form(START, 0.2, -0.1, 0.0, 3.7), 1e-9)


@pytest.mark.parametrize("motion", sorted(MOTIONS))
def test_no_disturbance_follows_the_closed_form(motion):
    vehicle, cmd = MOTIONS[motion]
    end = _drive(_sim(vehicle), cmd, 6.0)
    _same_pose(end, closed_form(START, *cmd.as_tuple(), 6.0), 1e-9)


@pytest.mark.parametrize("motion", sorted(MOTIONS))
@pytest.mark.parametrize("preset", ["bias", "slip"])
def test_constant_disturbances_follow_the_closed_form(motion, preset):
    vehicle, cmd = MOTIONS[motion]
    cfg = DISTURBANCE_PRESETS[preset]
    u = np.array(cmd.as_tuple())
    eff = u + cfg.bias - cfg.slip * u  # u + d, constant
    if vehicle == "unicycle":
        eff[1] = 0.0
    end = _drive(_sim(vehicle, preset), cmd, 6.0)
    _same_pose(end, closed_form(START, *eff, 6.0), 1e-9)
    # ... and the disturbance visibly moved the vehicle away from the undisturbed path.
    assert np.linalg.norm(end[:2] - closed_form(START, *u, 6.0)[:2]) > 0.1


@pytest.mark.parametrize("motion", sorted(MOTIONS))
def test_sinusoidal_disturbance_against_the_continuous_model(motion):
    vehicle, cmd = MOTIONS[motion]
    cfg = DISTURBANCE_PRESETS["sinusoidal"]
    mask = np.array([1.0, 0.0 if vehicle == "unicycle" else 1.0, 1.0])
    u = np.array(cmd.as_tuple())
    T = 6.0
    end = _drive(_sim(vehicle, "sinusoidal"), cmd, T)
    w = 2 * math.pi / cfg.sin_period_s
    # theta in closed form: theta0 + omega t + A/w (cos(phi) - cos(w t + phi)).
    a_om = cfg.sin_omega_rps
    theta = START[2] + u[2] * T + a_om / w * (math.cos(SIN_PHASES[2]) - math.cos(w * T + SIN_PHASES[2]))
    assert abs(math.atan2(math.sin(end[2] - theta), math.cos(end[2] - theta))) < 1e-6

    def f(t, xi):  # eq. 1.7-1.8 with d(t)
        d = cfg.sin_amplitude * np.sin(w * t + SIN_PHASES) * mask
        v = (u + d) * mask
        c, s = math.cos(xi[2]), math.sin(xi[2])
        return [c * v[0] - s * v[1], s * v[0] + c * v[1], v[2]]

    ref = solve_ivp(f, (0.0, T), START, rtol=1e-11, atol=1e-12).y[:, -1]
    _same_pose(end, ref, 1e-5)  # midpoint sampling at the 10 ms step: O(h^2)


@pytest.mark.parametrize("preset", sorted(DISTURBANCE_PRESETS))
@pytest.mark.parametrize("vehicle", ["unicycle", "omni"])
def test_every_preset_enters_as_G_theta_u_plus_d(preset, vehicle):
    """Replaying the logged u + d through the closed-form arc of each step reproduces the trajectory."""
    sim = _sim(vehicle, preset, seed=3)
    cmds = [Command(0.3, 0.15, 0.5), Command(0.25, -0.1, -0.3), Command(0.0, 0.0, 0.8)]
    for k in range(30):
        sim.robot.apply(cmds[k % 3], 0.1)
    log = sim.ground_truth.disturbance_log()
    assert log.shape == (300, 8)
    assert np.allclose(np.diff(log[:, 0]), log[1:, 1])  # contiguous steps
    pose = np.array(START)
    for _, h, *ud in log:
        v = np.array(ud[:3]) + np.array(ud[3:])
        pose = closed_form(pose, *v, h)
    _same_pose(sim.ground_truth.pose(), pose, 1e-9)
    d = log[:, 5:]
    if vehicle == "unicycle":
        assert not d[:, 1].any() and not log[:, 3].any()  # no sideways channel at all
    assert (np.abs(d).max() == 0.0) == (preset == "none")


def test_noisy_disturbance_is_a_seeded_bounded_random_walk():
    cfg = DISTURBANCE_PRESETS["noisy"]
    a, b, c = (Disturbance(cfg, VehicleKind.OMNI, seed) for seed in (1, 1, 2))
    u = np.zeros(3)
    da = np.array([a.sample(0.0, u, 0.05) for _ in range(20000)])  # 1000 s
    db = np.array([b.sample(0.0, u, 0.05) for _ in range(20000)])
    dc = np.array([c.sample(0.0, u, 0.05) for _ in range(200)])
    assert np.array_equal(da, db)
    assert not np.array_equal(da[:200], dc)
    std = da[2000:].std(axis=0)
    assert np.allclose(std, cfg.noise_std, rtol=0.35)  # settles at the configured spread
    # A random walk: strongly correlated from one step to the next.
    x = da[:, 2] - da[:, 2].mean()
    assert (x[1:] * x[:-1]).mean() / (x * x).mean() > 0.99


def test_presets_are_sized_as_specified():
    p = DISTURBANCE_PRESETS
    assert set(p) == {"none", "bias", "sinusoidal", "slip", "noisy", "harsh"}
    assert 0.1 <= p["bias"].bias_omega_rps <= 0.2
    assert 0.03 <= p["bias"].bias_f_mps <= 0.05
    assert 0.1 <= p["slip"].slip_f <= 0.2
    h = p["harsh"]
    assert h.bias.any() and h.sin_amplitude.any() and h.slip.any() and h.noise_std.any()
    assert p["none"].is_zero


def test_parse_disturbance_presets_and_custom_values():
    assert parse_disturbance("bias") == DISTURBANCE_PRESETS["bias"]
    custom = parse_disturbance("bias_omega_rps=0.2, slip_f=0.1")
    assert custom.bias_omega_rps == 0.2 and custom.slip_f == 0.1 and custom.bias_f_mps == 0.0
    on_top = parse_disturbance("slip,bias_omega_rps=-0.1")
    assert on_top.slip_f == DISTURBANCE_PRESETS["slip"].slip_f and on_top.bias_omega_rps == -0.1
    assert parse_disturbance(custom) is custom
    for bad, match in [("gale", "preset"), ("bias_x=1", "setting"), ("bias_f_mps=fast", "not a number"),
                       ("bias,slip", "key=value"), ("slip_f=1.5", "fraction")]:
        with pytest.raises(ConfigError, match=match):
            parse_disturbance(bad)


def test_collision_stops_the_vehicle_at_the_wall():
    world = box_world(3.0)  # walls at x = +-3
    sim = _sim("unicycle", world=world, start=(0.0, 0.0, 0.0))
    radius = sim.vehicle_config.radius_m
    collided = False
    for _ in range(200):  # 0.5 m/s for 20 s: far more than the 2.8 m to the wall
        rep = sim.robot.apply(Command(0.5, 0.0, 0.0), 0.1)
        collided |= rep.collided
        x = sim.ground_truth.pose().x
        assert x <= 3.0 - radius + 1e-6  # never through, never into the wall
    assert collided
    assert sim.ground_truth.pose().x == pytest.approx(3.0 - radius, abs=1e-3)
    assert sim.ground_truth.collisions > 0
    # Turning on the spot at the wall is fine, backing away too.
    assert not sim.robot.apply(Command(0.0, 0.0, 1.0), 0.5).collided
    sim.ground_truth.set_pose((2.7, 0.0, math.pi))
    assert not sim.robot.apply(Command(0.3, 0.0, 0.0), 1.0).collided
    assert sim.ground_truth.pose().x == pytest.approx(2.4, abs=1e-6)


def test_one_long_fast_step_cannot_tunnel_through_a_wall():
    world = box_world(3.0)
    sim = _sim("omni", world=world, start=(0.0, 0.0, 0.0))
    rep = sim.robot.apply(Command(1.0, 1.0, 0.0), 10.0)
    assert rep.collided
    p = sim.ground_truth.pose()
    assert abs(p.x) < 3.0 and abs(p.z) < 3.0
    assert sim.ground_truth.clearance() >= sim.vehicle_config.radius_m - 1e-6


def test_commands_are_saturated_and_dt_validated():
    sim = _sim("omni")
    rep = sim.robot.apply(Command(5.0, 0.0, 0.0), 0.1)
    assert rep.saturated
    assert sim.ground_truth.pose().x == pytest.approx(START[0] + 0.1 * math.cos(START[2]), abs=1e-9)
    assert not sim.robot.apply(Command(0.2, 0.0, 0.0), 0.1).saturated
    for dt in (0.0, -1.0, float("nan")):
        with pytest.raises(ConfigError, match="dt"):
            sim.robot.apply(Command(0.1), dt)
    with pytest.raises(ConfigError):
        VehicleConfig(radius_m=-1)
    with pytest.raises(ConfigError, match="vehicle"):
        _sim("tank")


def test_disturbance_config_validation():
    with pytest.raises(ConfigError):
        DisturbanceConfig(noise_tau_s=0)
    with pytest.raises(ConfigError):
        DisturbanceConfig(bias_f_mps=float("inf"))
