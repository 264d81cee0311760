"""Rendering: agreement with K, determinism, exact visibility culling, feature-rich images."""

from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np
import pytest
from sim.sim_helpers import box_world

from topomap.camera import CameraIntrinsics
from topomap.errors import ConfigError
from topomap.sim.geometry import camera_from_world, project_world_points
from topomap.sim.render import PyBulletRenderer, Renderer, make_renderer
from topomap.sim.simulator import default_camera
from topomap.sim.world import Marker, generate_world

GREEN = (0, 255, 0)


def _marker_world():
    """A 12 m room with green balls around a camera at the origin looking along +x (theta = 0)."""
    rng = np.random.default_rng(1)
    markers = []
    # Spread over bearings and heights so that no two share an image window.
    for bearing in np.linspace(-0.42, 0.42, 7):
        for height in (0.35, 1.25):
            d = rng.uniform(2.0, 5.0)
            markers.append(Marker(d * math.cos(bearing), d * math.sin(bearing), height + rng.uniform(-0.1, 0.1), 0.03, GREEN))
    return box_world(6.0, tuple(markers))


def _centroids(img, predicted, win=12):
    out = []
    for u, v in predicted:
        u0, v0 = int(round(u)), int(round(v))
        patch = img[v0 - win : v0 + win + 1, u0 - win : u0 + win + 1]
        ys, xs = np.nonzero((patch == GREEN).all(axis=2))
        assert len(xs) >= 4, f"marker expected near ({u:.1f}, {v:.1f}) not found"
        out.append((xs.mean() + u0 - win, ys.mean() + v0 - win))
    return np.array(out)


@pytest.mark.parametrize(
    "camera",
    [
        default_camera(),  # 320x240, 60 deg, centred principal point
        CameraIntrinsics(300.0, 300.0, 140.3, 130.7, 320, 240),  # off-centre principal point
        CameraIntrinsics(250.0, 250.0, 119.5, 89.5, 240, 180),
    ],
    ids=["default", "off-centre", "240x180"],
)
def test_markers_appear_where_K_R_t_predicts(camera):
    world = _marker_world()
    pose = (0.0, 0.0, 0.0)
    with PyBulletRenderer(world, camera, 0.8, lighting=(1.0, 0.0)) as r:  # flat light: exact colours
        img = r.render(pose)
    P = np.array([[m.x, m.z, m.height_m] for m in world.markers])
    # K [R|t] by hand, independently of project_world_points.
    R, t = camera_from_world(pose, 0.8)
    uvw = (camera.K @ (P @ R.T + t).T).T
    predicted = uvw[:, :2] / uvw[:, 2:3]
    assert np.allclose(predicted, project_world_points(camera, pose, P, 0.8))
    inside = (predicted[:, 0] > 15) & (predicted[:, 0] < camera.width - 16) & (predicted[:, 1] > 15) & (predicted[:, 1] < camera.height - 16)
    assert inside.sum() >= 8
    predicted = predicted[inside]
    err = np.linalg.norm(_centroids(img, predicted) - predicted, axis=1)
    assert err.max() < 0.5, err  # the requirement is 1 px


def test_markers_at_other_headings():
    world = _marker_world()
    camera = default_camera()
    # Turn the whole scene: camera heading 1 rad, markers rotated by the same angle about the origin.
    c, s = math.cos(1.0), math.sin(1.0)
    turned = replace(world, markers=tuple(replace(m, x=c * m.x - s * m.z, z=s * m.x + c * m.z) for m in world.markers))
    with PyBulletRenderer(turned, camera, 0.8, lighting=(1.0, 0.0)) as r:
        img = r.render((0.0, 0.0, 1.0))
    P = np.array([[m.x, m.z, m.height_m] for m in turned.markers])
    predicted = project_world_points(camera, (0.0, 0.0, 1.0), P, 0.8)
    predicted = predicted[(predicted[:, 0] > 15) & (predicted[:, 0] < 304)]
    assert len(predicted) >= 8
    assert np.linalg.norm(_centroids(img, predicted) - predicted, axis=1).max() < 0.5


def _free_poses(world, n, rng):
    x0, z0, x1, z1 = world.bounds()
    poses = []
    while len(poses) < n:
        x, z = rng.uniform(x0, x1), rng.uniform(z0, z1)
        if world.is_free(x, z) and world.clearance(x, z) > 0.2:
            poses.append((x, z, rng.uniform(-math.pi, math.pi)))
    return poses


def test_culling_never_changes_the_image(world):
    poses = _free_poses(world, 25, np.random.default_rng(3))
    poses += [(p[0], p[1], math.atan2(q[1] - p[1], q[0] - p[0])) for p, q in zip(world.route("loop").points[:-1], world.route("loop").points[1:])]
    with PyBulletRenderer(world, default_camera(160, 120)) as r:
        for pose in poses:
            r.cull = True
            a = r.render(pose)
            hidden = int((~r._shown).sum())
            r.cull = False
            b = r.render(pose)
            assert np.array_equal(a, b), pose
            assert hidden > 0


def test_images_are_deterministic(world):
    poses = _free_poses(world, 3, np.random.default_rng(4))
    with PyBulletRenderer(world, default_camera()) as r1, PyBulletRenderer(generate_world(0), default_camera()) as r2:
        for pose in poses:
            a = r1.render(pose)
            assert a.shape == (240, 320, 3) and a.dtype == np.uint8
            assert np.array_equal(a, r2.render(pose))
            assert np.array_equal(a, r1.render(pose))


def test_images_are_feature_rich(world, renderer):
    orb = cv2.ORB_create(1000)
    p = world.route("loop").points
    for k in range(4):
        a, b = p[k], p[k + 1]
        heading = math.atan2(b[1] - a[1], b[0] - a[0])
        img = renderer.render((a[0] + 0.3 * (b[0] - a[0]), a[1] + 0.3 * (b[1] - a[1]), heading))
        n = len(orb.detect(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)))
        assert n >= 300, n


def test_renderer_registry_and_protocol(world):
    with make_renderer("pybullet", world, default_camera(80, 60)) as r:
        assert isinstance(r, Renderer)
        assert r.render((12.0, 8.0, 0.0)).shape == (60, 80, 3)
    with pytest.raises(ConfigError, match="pybullet"):
        make_renderer("mujoco", world, default_camera())


def test_renderer_rejects_cameras_it_cannot_honour(world):
    with pytest.raises(ConfigError, match="distortion"):
        PyBulletRenderer(world, CameraIntrinsics(200, 200, 160, 120, 320, 240, distortion=(0.1, 0, 0, 0, 0)))
    with pytest.raises(ConfigError, match="image size"):
        PyBulletRenderer(world, CameraIntrinsics(200, 200, 160, 120))
    with pytest.raises(ConfigError, match="camera height"):
        PyBulletRenderer(world, default_camera(), camera_height_m=3.0)
    r = PyBulletRenderer(world, default_camera(80, 60))
    r.close()
    with pytest.raises(ConfigError, match="closed"):
        r.render((12.0, 8.0, 0.0))


def test_a_floor_of_texture_variants_does_not_verify_another_place():
    # one floor texture tiled every 2 m matches itself pixel for pixel everywhere: from world 257's
    # office a view of the floor verified a place 16 m away with 17-21 inliers, all on the floor
    from topomap.config import BuildConfig
    from topomap.features import extract
    from topomap.images import to_gray_u8
    from topomap.matching import verify

    cfg = BuildConfig()
    office = generate_world(257, style="office")
    assert office.tile_variants > 1
    elsewhere, here = (9.66, 23.75, math.pi), (9.84, 7.66, 0.2)
    looks = [(here[0], here[1], here[2] + math.radians(a)) for a in (150, 165, 180)]
    inliers = {}
    for variants in (1, office.tile_variants):
        with PyBulletRenderer(replace(office, tile_variants=variants), default_camera()) as r:
            features = [extract(to_gray_u8(r.render(p)), cfg.features) for p in [elsewhere, *looks]]
            inliers[variants] = [verify(f, features[0], cfg.match).inliers for f in features[1:]]
    assert min(inliers[1]) >= cfg.match.min_inliers  # the premise: the periodic floor aliases
    assert max(inliers[office.tile_variants]) < cfg.match.min_inliers


def test_tile_variants_keep_the_floor_and_leave_a_periodic_world_as_it_was(world):
    from topomap.sim import textures as tx
    from topomap.sim.render import _tile_cells, _tile_variant

    periodic = replace(world, tile_variants=1)
    with PyBulletRenderer(world, default_camera(160, 120)) as r1, PyBulletRenderer(periodic, default_camera(160, 120)) as r2:
        pose = world.route("loop").points[0]
        a, b = r1.render((pose[0], pose[1], 0.3)), r2.render((pose[0], pose[1], 0.3))
        assert a.shape == b.shape and not np.array_equal(a[80:], b[80:])  # the floor differs ...
        assert len(r2._floor_bodies) == len(world.free)  # ... and the periodic world is drawn as before
    # a variant is the same floor: its base colour, other details; a photograph is turned or mirrored
    base, other = tx.texture_variant(world.floor_texture, 0), tx.texture_variant(world.floor_texture, 3)
    assert np.array_equal(base, tx.texture_image(world.floor_texture)) and not np.array_equal(base, other)
    assert np.abs(np.median(base.reshape(-1, 3), 0) - np.median(other.reshape(-1, 3), 0)).max() < 30
    photo = next(w.texture for w in world.walls if w.texture.startswith("photo:"))
    img = tx.texture_image(photo)
    assert np.array_equal(tx.texture_variant(photo, 1), np.rot90(img, 1))
    assert np.array_equal(tx.texture_variant(photo, 4), img[:, ::-1])
    # cells cut at the texture's period cover the free floor exactly, and their variants spread
    cells = _tile_cells(world, tx.FLOOR_TILE_M)
    area = sum((c[2] - c[0]) * (c[3] - c[1]) for c in cells)
    assert area == pytest.approx(sum((f.x1 - f.x0) * (f.z1 - f.z0) for f in world.free))
    used = {_tile_variant((c[0] + c[2]) / 2, (c[1] + c[3]) / 2, tx.FLOOR_TILE_M, world.tile_variants) for c in cells}
    assert len(used) >= world.tile_variants // 2
