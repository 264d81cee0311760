"""Teach runs: files, formats, determinism, the path follower."""

from __future__ import annotations

import csv
import math

import cv2
import numpy as np
import pytest

from topomap.camera import load_camera
from topomap.errors import ConfigError, DatasetError
from topomap.sim.simulator import default_camera
from topomap.sim.teach import PurePursuit, TeachConfig, teach
from topomap.sim.world import load_world


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_teach_writes_images_poses_and_camera(taught, world):
    out = taught.out_dir
    rows = _rows(out / "poses.csv")
    assert list(rows[0]) == ["image", "x", "z", "theta"]
    images = sorted(p.name for p in out.glob("*.png"))
    assert images == [r["image"] for r in rows] == [f"{i:04d}.png" for i in range(taught.frames)]
    assert taught.frames >= 15
    img = cv2.imread(str(out / images[-1]))
    assert img.shape == (240, 320, 3)
    cam = load_camera(out / "camera.yaml")
    assert np.allclose(cam.K, default_camera().K) and (cam.width, cam.height) == (320, 240)
    assert load_world(out / "world.json") == world
    assert taught.collisions == 0


def test_taught_poses_follow_the_route(taught, world):
    route = world.route("room3").points
    poses = np.array([[float(r["x"]), float(r["z"]), float(r["theta"])] for r in _rows(taught.poses_path)])
    assert np.allclose(poses[0, :2], route[0], atol=1e-9)
    assert np.linalg.norm(poses[-1, :2] - route[-1]) < 0.1
    for p in poses:
        d = min(_point_segment(p[:2], a, b) for a, b in zip(route[:-1], route[1:]))
        assert d < 0.35
    steps = np.linalg.norm(np.diff(poses[:, :2], axis=0), axis=1)
    turns = np.abs(np.angle(np.exp(1j * np.diff(poses[:, 2]))))
    assert ((steps >= 0.25 - 0.02) | (turns >= math.radians(10) - 1e-3))[:-1].all()  # the spacing rule
    assert steps.max() < 0.3


def _point_segment(p, a, b):
    t = np.clip(np.dot(p - a, b - a) / np.dot(b - a, b - a), 0, 1)
    return float(np.linalg.norm(p - (a + t * (b - a))))


def test_poses_csv_reads_with_the_ground_truth_loader(taught):
    groundtruth = pytest.importorskip("topomap.groundtruth")
    table = groundtruth.read_poses(taught.poses_path)
    assert len(table.values) == taught.frames


def test_teach_is_deterministic(taught, world, tmp_path):
    again = teach(world, "room3", tmp_path / "again")
    assert again.frames == taught.frames
    assert (again.poses_path.read_bytes() == taught.poses_path.read_bytes())
    for name in ("0000.png", f"{taught.frames - 1:04d}.png"):
        assert (tmp_path / "again" / name).read_bytes() == (taught.out_dir / name).read_bytes()


def test_teach_refuses_to_overwrite(taught, world):
    with pytest.raises(DatasetError, match="already holds"):
        teach(world, "room3", taught.out_dir)


def test_teach_overwrite_with_other_spacing(tmp_path, world):
    out = tmp_path / "run"
    first = teach(world, "room3", out, spacing_m=0.5, vehicle="omni", disturbance="harsh", seed=2)
    second = teach(world, "room3", out, spacing_m=1.0, overwrite=True)
    assert second.frames < first.frames
    assert len(list(out.glob("*.png"))) == second.frames  # stale images removed


def test_pure_pursuit_follows_a_closed_path_in_order():
    square = np.array([[0, 0], [4, 0], [4, 4], [0, 4], [0, 0], [2, 0]], dtype=float)
    f = PurePursuit(square)
    pose = np.array([0.0, 0.0, 0.0])
    visited = []
    for _ in range(5000):
        cmd = f.command(pose)
        if cmd is None:
            break
        v, w, h = cmd.v_f, cmd.omega, 0.05
        pose = pose + h * np.array([v * math.cos(pose[2]), v * math.sin(pose[2]), w])
        visited.append(pose[:2].copy())
    assert cmd is None
    visited = np.array(visited)
    assert np.linalg.norm(visited[-1] - [2, 0]) < 0.1
    assert visited[:, 0].max() > 3.7 and visited[:, 1].max() > 3.7  # went round, did not short-cut


def test_teach_config_validation():
    for bad in (dict(spacing_m=0), dict(speed_mps=-1), dict(spacing_m=50), dict(overlap_m=-1)):
        with pytest.raises(Exception) as e:
            TeachConfig(**bad)
        assert "teach" in str(e.value)


def test_teach_runs_stay_countable(world, tmp_path, monkeypatch):
    for kw, match in (({"spacing_m": 1e-6}, "too small"), ({"dt_s": 1e-7}, "too small"), ({"speed_mps": 1e-9}, "too small"),
                      ({"turn_spacing_deg": 0.0}, "positive")):
        with pytest.raises(ConfigError, match=match):
            TeachConfig(**kw)
    import sys

    monkeypatch.setattr(sys.modules["topomap.sim.teach"], "MAX_TEACH_IMAGES", 100)
    with pytest.raises(ConfigError, match="images, more than 100; use a larger --spacing"):
        teach(world, "loop", tmp_path / "t", spacing_m=0.05)
    assert not (tmp_path / "t" / "poses.csv").exists()
