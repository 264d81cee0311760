"""topomap.camera: default intrinsics, scaling, normalise/project round trips, camera files."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
from conftest import dataset

from topomap.camera import DEFAULT_HFOV_DEG, CameraIntrinsics, load_camera
from topomap.errors import DatasetError


@pytest.fixture
def cam():
    return CameraIntrinsics(500.0, 510.0, 319.5, 239.5, 640, 480, source="test")


def test_default_intrinsics():
    c = CameraIntrinsics.default(640, 480)
    assert c.source == "default" and (c.width, c.height) == (640, 480)
    assert c.fx == c.fy == pytest.approx(320.0 / math.tan(math.radians(30.0)))
    assert (c.cx, c.cy) == (319.5, 239.5)  # OpenCV pixel-centre convention
    assert c.hfov_deg == pytest.approx(DEFAULT_HFOV_DEG)
    with pytest.raises(DatasetError, match="default camera"):
        CameraIntrinsics.default(0, 480)


def test_invalid_parameters_raise():
    with pytest.raises(DatasetError, match="fx"):
        CameraIntrinsics(0.0, 1.0, 0.0, 0.0)
    with pytest.raises(DatasetError, match="fy"):
        CameraIntrinsics(1.0, float("nan"), 0.0, 0.0)
    with pytest.raises(DatasetError, match="cx"):
        CameraIntrinsics(1.0, 1.0, float("inf"), 0.0)
    with pytest.raises(DatasetError, match="3x3"):
        CameraIntrinsics.from_matrix(np.eye(4))


def test_scaled_maps_pixel_centres(cam):
    s = cam.scaled(0.5)
    assert (s.width, s.height) == (320, 240) and s.fx == 250.0 and s.fy == 255.0
    # a 3-D point projects to pixel p in the full image and to (p + 0.5) * 0.5 - 0.5 in the half image
    P = np.array([[0.3, -0.2, 2.0], [-1.0, 0.5, 4.0]])
    np.testing.assert_allclose(s.project(P), (cam.project(P) + 0.5) * 0.5 - 0.5, atol=1e-9)
    assert s.scaled(2.0).cx == pytest.approx(cam.cx)


def test_fitted_to(cam):
    assert cam.fitted_to(640, 480) is cam
    f = cam.fitted_to(1280, 960)
    assert (f.width, f.height) == (1280, 960) and f.fx == pytest.approx(1000.0)
    unknown = CameraIntrinsics(500.0, 500.0, 300.0, 200.0)  # size 0: taken to describe the given size
    g = unknown.fitted_to(800, 600)
    assert (g.width, g.height, g.fx, g.cx) == (800, 600, 500.0, 300.0)


def test_normalize_project_round_trip(cam):
    rng = np.random.default_rng(0)
    P = np.column_stack([rng.uniform(-2, 2, 50), rng.uniform(-1, 1, 50), rng.uniform(1, 10, 50)])
    px = cam.project(P)
    np.testing.assert_allclose(cam.normalize(px), P[:, :2] / P[:, 2:3], atol=1e-12)
    assert cam.normalize(np.zeros((0, 2))).shape == (0, 2)
    # bearings: positive to the right, atan2(X, Z)
    np.testing.assert_allclose(cam.bearing(px), np.arctan2(P[:, 0], P[:, 2]), atol=1e-12)
    assert cam.bearing(np.array([[cam.cx + 100.0, cam.cy]]))[0] > 0


def test_normalize_undistorts():
    dist = (-0.2, 0.05, 0.001, -0.001, 0.0)
    c = CameraIntrinsics(400.0, 400.0, 320.0, 240.0, 640, 480, distortion=dist)
    assert c.has_distortion
    rng = np.random.default_rng(1)
    xy = np.column_stack([rng.uniform(-0.5, 0.5, 30), rng.uniform(-0.4, 0.4, 30)])
    obj = np.column_stack([xy, np.ones(30)])
    px, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), c.K, c.dist)
    np.testing.assert_allclose(c.normalize(px.reshape(-1, 2)), xy, atol=1e-5)


def test_dict_round_trip(cam):
    d = cam.to_dict()
    assert CameraIntrinsics.from_dict(d) == cam
    json.dumps(d)  # JSON-able
    plain = CameraIntrinsics.from_dict({"fx": 1, "fy": 2, "cx": 3, "cy": 4, "distortion": {"k1": 0.1}})
    assert plain.distortion == (0.1, 0.0, 0.0, 0.0, 0.0)
    with pytest.raises(DatasetError, match="lacks 'cy'"):
        CameraIntrinsics.from_dict({"fx": 1, "fy": 2, "cx": 3})
    with pytest.raises(DatasetError, match="non-numeric"):
        CameraIntrinsics.from_dict({"fx": "wide", "fy": 2, "cx": 3, "cy": 4})


@pytest.mark.parametrize("suffix", [".yaml", ".json"])
def test_save_load_round_trip(tmp_path, cam, suffix):
    path = cam.save(tmp_path / f"cam{suffix}")
    back = load_camera(path)
    assert (back.fx, back.fy, back.cx, back.cy, back.width, back.height) == (500.0, 510.0, 319.5, 239.5, 640, 480)


def test_load_plain_yaml_and_opencv_yaml(tmp_path):
    (tmp_path / "c.yml").write_text("fx: 600\nfy: 601\ncx: 320\ncy: 240\ndistortion: [0.1, -0.01]\n")
    c = load_camera(tmp_path / "c.yml")
    assert (c.fx, c.fy, c.cx, c.cy) == (600.0, 601.0, 320.0, 240.0)
    assert c.distortion == (0.1, -0.01, 0.0, 0.0, 0.0) and c.source == "c.yml"
    (tmp_path / "ocv.yaml").write_text(
        "%YAML:1.0\nimage_width: 640\nimage_height: 480\n"
        "camera_matrix: {rows: 3, cols: 3, data: [700, 0, 330, 0, 710, 250, 0, 0, 1]}\n"
        "distortion_coefficients: {rows: 1, cols: 5, data: [0.01, 0, 0, 0, 0]}\n"
    )
    o = load_camera(tmp_path / "ocv.yaml")
    assert (o.fx, o.fy, o.cx, o.cy, o.width, o.height) == (700.0, 710.0, 330.0, 250.0, 640, 480)
    assert o.distortion[0] == 0.01


def test_load_castle_k_txt_and_kitti(tmp_path):
    k = dataset("castle-p30") / "K.txt"
    c = load_camera(k)
    assert (c.fx, c.fy, c.cx, c.cy) == (689.87, 691.04, 380.1725, 251.7025)
    assert c.source == "K.txt" and (c.width, c.height) == (0, 0)
    (tmp_path / "calib.txt").write_text("P0: 718.8 0 607.2 0 0 718.8 185.2 0 0 0 1 0\nP1: 1 2 3\n")
    kc = load_camera(tmp_path / "calib.txt")
    assert (kc.fx, kc.cx, kc.cy) == (718.8, 607.2, 185.2)


def test_bad_camera_files(tmp_path):
    with pytest.raises(DatasetError, match="does not exist"):
        load_camera(tmp_path / "none.yaml")
    (tmp_path / "bad.json").write_text("{fx: ")
    with pytest.raises(DatasetError, match="not valid YAML/JSON"):
        load_camera(tmp_path / "bad.json")
    (tmp_path / "list.yaml").write_text("- 1\n- 2\n")
    with pytest.raises(DatasetError, match="mapping"):
        load_camera(tmp_path / "list.yaml")
    (tmp_path / "partial.yaml").write_text("fx: 1\nfy: 1\n")
    with pytest.raises(DatasetError, match="lacks 'cx'"):
        load_camera(tmp_path / "partial.yaml")
