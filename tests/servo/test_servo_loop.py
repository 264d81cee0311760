"""AppearanceServo end to end: synthetic 3D points projected into the current and goal cameras at
every step, pixel noise and outliers, the servo's command driving the kinematic vehicle with unknown
disturbances; convergence within 0.05 m / 3 deg (docs/theory.md section 3)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from servo_synth import CAMERA, disturbance, matches, median_goal_depth, room_points, servo_episode

from topomap.config import SERVO_PRESETS, ServoConfig, servo_preset
from topomap.errors import ConfigError
from topomap.motion import STOP, Command, VehicleKind
from topomap.servo import AppearanceServo, PoseStatus, ServoStatus
from topomap.servo.disturbance import DisturbanceEstimate
from topomap.servo.servo import PoseWindow

POINTS = room_points(np.random.default_rng(7))
GOAL = (0.5, -0.3, 0.2)


def in_world(rel, goal=GOAL):
    c, s = math.cos(goal[2]), math.sin(goal[2])
    return (goal[0] + c * rel[0] - s * rel[1], goal[1] + s * rel[0] + c * rel[1], goal[2] + rel[2])


@pytest.mark.slow
@pytest.mark.parametrize("vehicle", ["unicycle", "omni"])
@pytest.mark.parametrize("rel", [(-1.5, 0.4, 0.3), (0.6, -0.3, -0.2)])
def test_servo_converges_from_images_under_harsh_disturbances(vehicle, rel):
    rng = np.random.default_rng(1)
    servo = AppearanceServo(vehicle, servo_preset("default"))
    final, outs = servo_episode(servo, POINTS, in_world(rel), GOAL, disturbance("harsh", 2), rng, t_max=30.0)
    assert math.hypot(final[0], final[1]) < 0.05, final
    assert abs(math.degrees(final[2])) < 3.0, final
    assert outs[-1].converged and outs[-1].status is ServoStatus.CONVERGED
    assert all(o.status is not ServoStatus.LOST for o in outs)
    assert all(abs(o.command.v_h) == 0 for o in outs) or vehicle == "omni"
    # the observer learned d_omega's constant part (0.15 rad/s, +-0.05 sinusoid, random walk)
    assert 0.0 < np.median([o.disturbance.d_omega for o in outs[100:]]) < 0.35


@pytest.mark.slow
def test_compensation_beats_the_uncompensated_servo_from_images():
    finals = {}
    for preset in ("default", "uncompensated"):
        rng = np.random.default_rng(3)
        servo = AppearanceServo("unicycle", servo_preset(preset))
        final, _ = servo_episode(servo, POINTS, in_world((-1.2, 0.3, 0.2)), GOAL, disturbance("bias", 0), rng, t_max=30.0)
        finals[preset] = final
    comp, nominal = finals["default"], finals["uncompensated"]
    assert math.hypot(comp[0], comp[1]) * 3 < math.hypot(nominal[0], nominal[1])
    assert abs(comp[2]) * 3 < abs(nominal[2])


def test_converged_flag_matches_the_true_pose_when_declared():
    rng = np.random.default_rng(4)
    servo = AppearanceServo("omni")
    final, outs = servo_episode(servo, POINTS, in_world((-0.5, 0.2, 0.1)), GOAL, disturbance("none"), rng,
                                t_max=30.0, stop_when_converged=True)
    assert outs[-1].converged
    assert math.hypot(final[0], final[1]) < 0.05 and abs(math.degrees(final[2])) < 3.0


def test_lost_geometry_stops_the_vehicle():
    servo = AppearanceServo("unicycle")
    out = servo.step(np.zeros((2, 2)), np.zeros((2, 2)), CAMERA, 0.1)
    assert out.status is ServoStatus.LOST and out.command == STOP and not out.converged
    assert out.pose.status is PoseStatus.TOO_FEW_POINTS and math.isnan(out.heading_error_rad)


def test_pure_rotation_aligns_in_place():
    rng = np.random.default_rng(5)
    cp, gp, _ = matches(POINTS, in_world((0.0, 0.0, 0.3)), GOAL, rng, noise_px=0.5)
    out = AppearanceServo("unicycle").step(cp, gp, CAMERA, 0.1)
    assert out.pose.status is PoseStatus.PURE_ROTATION and out.status is ServoStatus.ALIGNING
    assert out.position_error_s == 0.0
    assert out.command.omega < 0 and abs(out.command.v_f) < 1e-9  # turn back clockwise, no driving


def test_retarget_keeps_the_disturbance_estimate():
    rng = np.random.default_rng(6)
    servo = AppearanceServo("unicycle")
    servo_episode(servo, POINTS, in_world((-1.0, 0.0, 0.0)), GOAL, disturbance("omega"), rng, t_max=8.0)
    d = servo.observer.estimate.d_omega
    assert d == pytest.approx(0.15, abs=0.03)
    servo.retarget()
    assert servo.observer.estimate.d_omega == d and math.isnan(servo.observer.estimate.theta)


def test_bad_arguments_are_clear_errors():
    with pytest.raises(ConfigError, match="choose one of: omni, unicycle"):
        AppearanceServo("tank")
    with pytest.raises(ConfigError, match="dt"):
        AppearanceServo("omni").step(np.zeros((5, 2)), np.zeros((5, 2)), CAMERA, 0.0)
    with pytest.raises(ConfigError, match="ServoConfig"):
        AppearanceServo("omni", {"gamma": 1})
    assert AppearanceServo(VehicleKind.OMNI).vehicle is VehicleKind.OMNI


def test_first_step_without_last_command():
    rng = np.random.default_rng(8)
    cp, gp, _ = matches(POINTS, in_world((-1.0, 0.3, 0.2)), GOAL, rng, noise_px=0.5)
    out = AppearanceServo("unicycle").step(cp, gp, CAMERA, 0.1, None)
    assert out.status is ServoStatus.APPROACHING and isinstance(out.command, Command)
    assert out.command.v_f > 0  # the goal is ahead
    assert out.inliers > 50 and out.position_error_m == pytest.approx(out.position_error_s * 3.0)


def test_presets_build_working_servos():
    rng = np.random.default_rng(9)
    cp, gp, _ = matches(POINTS, in_world((-1.0, 0.3, 0.2)), GOAL, rng, noise_px=0.5)
    for name, cfg in SERVO_PRESETS.items():
        out = AppearanceServo("unicycle", cfg).step(cp, gp, CAMERA, 0.1)
        assert out.status is ServoStatus.APPROACHING, name


def test_a_known_goal_scale_makes_distances_metric():
    """retarget(scale_m=...) measures the goal in metres: with the true median depth of the goal's
    points, position_error_m is the true distance; the nominal scale gets it wrong by their ratio."""
    rng = np.random.default_rng(8)
    rel = (-0.6, 0.2, 0.05)
    cp, gp, idx = matches(POINTS, in_world(rel), GOAL, rng, noise_px=0.2)
    depth = median_goal_depth(POINTS, GOAL, idx)
    nominal = AppearanceServo("omni").step(cp, gp, CAMERA, 0.1)
    servo = AppearanceServo("omni")
    servo.retarget(scale_m=depth)
    metric = servo.step(cp, gp, CAMERA, 0.1)
    true = math.hypot(rel[0], rel[1])
    assert metric.position_error_m == pytest.approx(true, rel=0.1)
    assert nominal.position_error_m == pytest.approx(true * servo.config.nominal_scale_m / depth, rel=0.1)
    servo.retarget()
    assert servo.scale_m == servo.config.nominal_scale_m


def test_blind_servo_turns_back_toward_the_goal_heading():
    """Lost (no geometry) with a dead-reckoned heading error, the compensating servo turns in place
    toward the goal's heading (and cancels d_omega); the uncompensated baseline just stops."""
    from topomap.servo.disturbance import DisturbanceEstimate

    est = DisturbanceEstimate(d_omega=0.1, d_omega_std=0.01, theta=0.4, kappa=1 / 3.0)
    for vehicle in ("unicycle", "omni"):
        cmd = AppearanceServo(vehicle).reacquire_command(est)
        assert cmd.omega == pytest.approx(-1.0 * 0.4 - 0.1) and cmd.v_f == 0.0 and cmd.v_h == 0.0
    aligned = DisturbanceEstimate(d_omega=0.1, d_omega_std=0.01, theta=0.0, kappa=1 / 3.0)
    assert AppearanceServo("omni").reacquire_command(aligned).omega == pytest.approx(-0.1)  # hold only
    assert AppearanceServo("omni", servo_preset("uncompensated")).reacquire_command(est) == STOP


def test_retarget_with_a_heading_prior_turns_toward_an_unseen_goal():
    """A new subgoal out of view (a corner): with the predicted heading the blind servo turns toward
    it; without one it can only hold."""
    servo = AppearanceServo("unicycle")
    servo.observer.update(0.1, None, 0.2, None)
    for _ in range(20):  # the old goal seen steadily: d_omega known (zero)
        servo.observer.update(0.1, Command(), 0.2, None)
    servo.retarget(heading_prior_rad=0.6)
    none = np.zeros((0, 2))
    out = servo.step(none, none, CAMERA, 0.1, Command())
    assert out.status is ServoStatus.LOST and out.command.omega < -0.3
    servo.retarget()
    assert servo.step(none, none, CAMERA, 0.1, Command()).command.omega == pytest.approx(0.0, abs=0.05)


def test_the_pose_window_ignores_a_jump_and_follows_the_motion():
    """One image's pose off by metres (a close wall) does not reach the laws; a robot driving at
    0.3 m/s is followed without lag (each held pose is moved on by the predicted motion)."""
    est = DisturbanceEstimate(kappa=1.0 / 3.0)  # scaled units of 3 m
    window = PoseWindow(5)
    drive = Command(0.3, 0.0, 0.0)
    seen = []
    for k in range(12):
        window.predict(drive, est, 0.1)
        x = -1.0 + 0.01 * k  # 0.3 m/s = 0.1 scaled/s
        measured = x + (2.5 if k == 8 else 0.0)  # one reconstruction 7.5 m off
        seen.append(window.add(measured, 0.0, 0.0)[0] - x)
    assert max(abs(e) for e in seen) < 1e-9
    # a turn is followed as well, and poses older than the window are forgotten
    window.clear()
    for k in range(8):
        window.predict(Command(0.0, 0.0, 0.5), est, 0.1)
        theta = 0.05 * k
        assert abs(window.add(0.0, 0.0, theta)[2] - theta) < 1e-9
    assert len(window._poses) == 5


def test_a_window_of_one_is_the_raw_pose():
    window = PoseWindow(1)
    est = DisturbanceEstimate(kappa=1.0 / 3.0)
    for x in (0.4, 3.0, -2.0):
        window.predict(Command(0.3, 0.0, 0.2), est, 0.1)
        assert window.add(x, 0.1, 0.2) == (x, 0.1, 0.2)


def test_one_image_from_elsewhere_is_reported_but_does_not_steer():
    """The step reports each image's own measurement (arrival tests count images as independent
    witnesses), while the command comes from the window's median pose: an image that puts the robot
    a metre off for one period turns nothing."""
    rng = np.random.default_rng(3)
    here, elsewhere = in_world((-0.8, 0.1, 0.05)), in_world((-1.8, -0.9, 0.05))
    runs = {}
    for window in (1, 5):
        servo = AppearanceServo("omni", ServoConfig(pose_window=window))
        cmd, outs = STOP, []
        for k in range(6):
            cp, gp, _ = matches(POINTS, elsewhere if k == 5 else here, GOAL, rng, noise_px=0.2)
            outs.append(servo.step(cp, gp, CAMERA, 0.1, cmd))  # cmd not applied: the robot stands still
            cmd = STOP
        runs[window] = outs
    raw, med = runs[1][-1], runs[5][-1]
    assert abs(med.position_error_s - raw.position_error_s) < 0.02  # the jump is reported as measured
    assert raw.position_error_s > 1.5 * runs[1][-2].position_error_s
    before = runs[5][-2].command
    assert math.hypot(med.command.v_f - before.v_f, med.command.v_h - before.v_h) < 0.02
    assert math.hypot(raw.command.v_f - before.v_f, raw.command.v_h - before.v_h) > 0.05


def test_a_measured_pose_steers_unless_the_features_agree_with_it():
    """``measured`` (the near floor's pose) replaces the features' pose; with ``features_within_s``
    the features' own pose is kept where it lies that close to it (the finer witness on a good
    view) and the measured one is used where they disagree by more."""
    from topomap.servo.pose import RelativePose

    rng = np.random.default_rng(5)
    rel = (-0.6, 0.2, 0.05)
    cp, gp, _ = matches(POINTS, in_world(rel), GOAL, rng, noise_px=0.2)
    features = AppearanceServo("omni").step(cp, gp, CAMERA, 0.1)
    x, z = features.pose.x_s, features.pose.z_s
    for offset, gate, used in ((0.05, None, "measured"), (0.05, 0.2, "features"), (0.5, 0.2, "measured")):
        measured = RelativePose(PoseStatus.OK, theta=features.pose.theta, x_s=x + offset, z_s=z, inliers=500)
        out = AppearanceServo("omni").step(cp, gp, CAMERA, 0.1, measured=measured, features_within_s=gate)
        expect = measured if used == "measured" else features.pose
        assert out.pose.x_s == pytest.approx(expect.x_s, abs=1e-9), (offset, gate)
        assert out.position_error_s == pytest.approx(math.hypot(expect.x_s, expect.z_s), abs=1e-9)
