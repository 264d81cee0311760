"""The simulator facade: the robot/ground-truth boundary, determinism, validation."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from topomap.errors import ConfigError
from topomap.motion import Command, VehicleKind
from topomap.sim.simulator import GroundTruth, Robot, RobotInterface, Simulator, StepReport, default_camera, route_start


def _drive(sim, n=20):
    cmds = [Command(0.3, 0.0, 0.2), Command(0.3, 0.0, -0.2)]
    return [sim.robot.apply(cmds[(k // 5) % 2], 0.1) for k in range(n)]


def test_robot_side_has_images_and_commands_but_no_pose(world, renderer):
    with Simulator(world, vehicle="omni", disturbance="harsh", seed=1, renderer=renderer) as sim:
        robot = sim.robot
        assert isinstance(robot, Robot) and isinstance(robot, RobotInterface)
        assert robot.kind is VehicleKind.OMNI
        assert robot.camera == default_camera()
        public = {n for n in dir(robot) if not n.startswith("_")}
        assert public == {"apply", "camera", "camera_height_m", "kind", "render"}  # mounting, not pose
        assert robot.camera_height_m == pytest.approx(0.8)
        with pytest.raises(AttributeError):
            robot.pose = (0, 0, 0)  # __slots__: nothing can be hung on it either
        img = robot.render()
        assert type(img) is np.ndarray and img.base is None and img.flags.owndata
        assert img.shape == (240, 320, 3) and img.dtype == np.uint8
        rep = robot.apply(Command(0.2, 0.0, 0.0), 0.1)
        assert isinstance(rep, StepReport)
        assert {f.name for f in dataclasses.fields(rep)} == {"collided", "saturated", "time_s", "dt_s"}
        assert rep.time_s == pytest.approx(0.1)
        # Ground truth lives on the other side.
        assert isinstance(sim.ground_truth, GroundTruth)
        assert len(sim.ground_truth.pose()) == 3


def test_ground_truth_side(world, renderer):
    with Simulator(world, disturbance="bias", renderer=renderer) as sim:
        start = route_start(world, "loop")
        assert sim.ground_truth.pose() == pytest.approx(start)
        _drive(sim, 10)
        traj = sim.ground_truth.trajectory()
        assert traj.shape == (11, 4)
        assert traj[-1, 0] == pytest.approx(1.0)
        assert np.allclose(traj[-1, 1:], sim.ground_truth.pose())
        assert sim.ground_truth.disturbance() == pytest.approx([0.04, 0.0, 0.15])  # unicycle: no d_h
        assert sim.ground_truth.clearance() > 0.5
        # Rendering at the true pose equals what the robot sees.
        assert np.array_equal(sim.ground_truth.render(), sim.robot.render())


def test_same_seed_same_run_other_seed_other_run(world, renderer):
    def run(seed):
        with Simulator(world, disturbance="noisy", seed=seed, renderer=renderer) as sim:
            _drive(sim, 30)
            return sim.ground_truth.trajectory(), sim.robot.render()

    (t1, i1), (t2, i2), (t3, _) = run(5), run(5), run(6)
    assert np.array_equal(t1, t2) and np.array_equal(i1, i2)
    assert not np.array_equal(t1, t3)


def test_start_pose_validation(world):
    x0, z0, _, _ = world.bounds()
    with pytest.raises(ConfigError, match="inside a wall"):
        Simulator(world, start_pose=(x0 - 5.0, z0 - 5.0, 0.0))
    with pytest.raises(ConfigError, match="finite"):
        Simulator(world, start_pose=(math.nan, 0.0, 0.0))
    with Simulator(world, start_pose=route_start(world, "room1")) as sim:
        assert sim.ground_truth.pose().x == pytest.approx(world.route("room1").points[0, 0])
        with pytest.raises(ConfigError, match="Command"):
            sim.robot.apply((0.1, 0.0, 0.0), 0.1)
        with pytest.raises(ConfigError, match="pose"):
            sim.ground_truth.set_pose((1.0, 2.0))


def test_given_renderer_is_shared_not_closed(world, renderer):
    with Simulator(world, renderer=renderer) as sim:
        assert sim.robot.camera == renderer.camera
    assert renderer.render(route_start(world)).shape == (240, 320, 3)  # still open
    with pytest.raises(ConfigError, match="camera"):
        Simulator(world, camera=default_camera(160, 120), renderer=renderer)


def test_unknown_renderer_and_disturbance(world):
    with pytest.raises(ConfigError, match="renderer"):
        Simulator(world, renderer="vulkan")
    with pytest.raises(ConfigError, match="disturbance"):
        Simulator(world, disturbance="storm")
