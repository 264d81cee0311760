"""topomap.matching: ratio/mutual matching with the registry's norm, epipolar verification."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from map_synth import scene, window

from topomap.config import FeatureConfig, MatchConfig
from topomap.errors import ConfigError
from topomap.features import Features, extract
from topomap.camera import CameraIntrinsics
from topomap.matching import Matches, Verification, match_descriptors, match_descriptors_grouped, scene_scale, verify


@pytest.fixture(scope="module")
def texture():
    return scene(seed=1)


@pytest.fixture(scope="module")
def pair(texture):
    """An image and a warped view of the same scene (shifted 40 px, zoomed 5 %, slightly rotated)."""
    a = window(texture, 300.0)
    h, w = a.shape
    R = cv2.getRotationMatrix2D((w / 2, h / 2), 3.0, 1.05)
    R[0, 2] += 40.0
    b = cv2.warpAffine(a, R, (w, h), borderMode=cv2.BORDER_REFLECT)
    return a, b, R


@pytest.mark.parametrize("kind", ["orb", "sift", "akaze"])
def test_warped_image_verifies_with_many_inliers(pair, kind):
    a, b, R = pair
    cfg = FeatureConfig(kind=kind, max_features=800)
    fa, fb = extract(a, cfg), extract(b, cfg)
    v = verify(fa, fb)
    assert v.inliers >= 150 and v.verified, v.inliers
    assert v.inlier_ratio > 0.7
    assert 0.2 < v.similarity <= 1.0
    assert v.F is not None and v.F.shape == (3, 3)
    # inliers obey the known warp (within a few pixels)
    m = v.inlier_matches
    pa, pb = fa.keypoints[m.ia], fb.keypoints[m.ib]
    pred = pa @ R[:, :2].T + R[:, 2]
    assert np.median(np.linalg.norm(pred - pb, axis=1)) < 2.0
    assert 25.0 < v.flow_px < 80.0  # shift of 40 px plus rotation / zoom about the centre


def test_unrelated_images_do_not_verify(texture):
    a = window(texture, 0.0)
    b = window(scene(seed=7), 0.0)
    fa, fb = extract(a), extract(b)
    v = verify(fa, fb)
    assert v.inliers == 0 and v.similarity == 0.0 and v.F is None and not v.verified
    far = extract(window(texture, 1800.0))  # same texture, no overlap
    assert verify(fa, far).inliers == 0


def test_matches_are_one_to_one_and_mutual(pair):
    a, b, _ = pair
    fa, fb = extract(a), extract(b)
    m = match_descriptors(fa, fb)
    assert len(m) > 100
    assert len(np.unique(m.ib)) == len(m) and len(np.unique(m.ia)) == len(m)
    assert m.ia.dtype == np.int32 and m.distance.dtype == np.float32
    loose = match_descriptors(fa, fb, MatchConfig(mutual=False, ratio=1.0))
    assert len(loose) >= len(m)
    # Hamming distances for ORB: integers in [0, 256]
    assert np.all(m.distance == np.round(m.distance)) and m.distance.max() <= 256


def test_verification_is_deterministic(pair):
    a, b, _ = pair
    fa, fb = extract(a), extract(b)
    v1, v2 = verify(fa, fb), verify(fa, fb)
    np.testing.assert_array_equal(v1.inlier_mask, v2.inlier_mask)
    assert v1.similarity == v2.similarity


def test_too_few_features_or_matches(pair):
    a, _, _ = pair
    fa = extract(a)
    empty = Features.empty("orb", (480, 360))
    assert len(match_descriptors(fa, empty)) == 0
    v = verify(fa, empty)
    assert v.inliers == 0 and v.F is None
    few = Matches(np.arange(5, dtype=np.int32), np.arange(5, dtype=np.int32), np.zeros(5, np.float32))
    assert verify(fa, fa, matches=few).inliers == 0  # below the 8-point minimum


def test_mixed_kinds_are_refused(pair):
    a, _, _ = pair
    with pytest.raises(ConfigError, match="cannot match orb features against sift"):
        match_descriptors(extract(a), extract(a, FeatureConfig(kind="sift", max_features=100)))


def test_grouped_matching_with_one_group_is_brute_force(pair):
    a, b, _ = pair
    fa, fb = extract(a), extract(b)
    brute = match_descriptors(fa, fb)
    one = match_descriptors_grouped(fa, fb, np.zeros(len(fa), int), np.zeros(len(fb), int))
    assert len(brute) > 100
    # the same pairs, up to how equal distances are broken (OpenCV keeps the first of a tie)
    pairs = lambda m: set(zip(m.ia.tolist(), m.ib.tolist()))  # noqa: E731
    assert len(pairs(brute) ^ pairs(one)) <= 0.01 * len(brute)


def test_grouped_matching_stays_within_groups_and_still_verifies(pair):
    a, b, _ = pair
    fa, fb = extract(a), extract(b)
    # groups by the first descriptor byte's top 3 bits: true matches mostly share them
    ga, gb = fa.descriptors[:, 0] >> 5, fb.descriptors[:, 0] >> 5
    m = match_descriptors_grouped(fa, fb, ga, gb, max_distance=64)
    assert np.all(ga[m.ia] == gb[m.ib]) and np.all(m.distance <= 64)
    assert len(np.unique(m.ib)) == len(m)  # one-to-one
    v = verify(fa, fb, matches=m)
    assert v.inliers >= 100 and v.inlier_ratio > 0.7
    # disjoint groups: nothing to match
    assert len(match_descriptors_grouped(fa, fb, np.zeros(len(fa), int), np.ones(len(fb), int))) == 0
    with pytest.raises(ValueError, match="one group per descriptor"):
        match_descriptors_grouped(fa, fb, ga[:-1], gb)


@pytest.mark.parametrize("kind", ["orb", "sift"])
def test_prosac_verifies_like_magsac(pair, kind):
    a, b, _ = pair
    cfg = FeatureConfig(kind=kind, max_features=800)
    fa, fb = extract(a, cfg), extract(b, cfg)
    magsac = verify(fa, fb)
    prosac = verify(fa, fb, MatchConfig(ransac_method="prosac", ransac_max_iters=1000))
    assert prosac.inliers >= 0.95 * magsac.inliers
    with pytest.raises(ConfigError, match="ransac_method"):
        MatchConfig(ransac_method="lmeds")


@pytest.mark.parametrize("zoom, angle", [(1.0, 4.0), (1.3, 0.0), (1.3, 5.0), (0.8, -3.0)])
def test_scene_scale_measures_the_zoom_not_the_rotation(texture, zoom, angle):
    """A view closer to the scene shows it larger: scene_scale reads the zoom between two views
    (what the epipolar inliers alone leave open) and ignores a rotation and shift."""
    a = window(texture, 300.0)
    h, w = a.shape
    R = cv2.getRotationMatrix2D((w / 2, h / 2), angle, zoom)
    R[0, 2] += 15.0
    b = cv2.warpAffine(a, R, (w, h), borderMode=cv2.BORDER_REFLECT)
    cam = CameraIntrinsics(fx=w, fy=w, cx=w / 2, cy=h / 2, width=w, height=h)  # ~53 deg across
    fa, fb = extract(a, FeatureConfig()), extract(b, FeatureConfig())
    v = verify(fb, fa)
    assert v.verified
    assert scene_scale(fb, fa, v, cam, cam) == pytest.approx(zoom, rel=0.05)
    back = verify(fa, fb)
    assert scene_scale(fa, fb, back, cam, cam) == pytest.approx(1.0 / zoom, rel=0.05)


def test_scene_scale_is_unchanged_by_turning_the_camera():
    """Rays turned by a yaw of 30 deg: pixel distances stretch toward the image's edge, the angles
    between the rays do not."""
    cam = CameraIntrinsics(fx=300.0, fy=300.0, cx=160.0, cy=120.0, width=320, height=240)
    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(-1, 1, 60), rng.uniform(-0.5, 0.5, 60), rng.uniform(4, 6, 60)])
    yaw = np.radians(30.0)
    R = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
    fa = Features(cam.project(pts).astype(np.float32), np.zeros((60, 32), np.uint8), "orb", (320, 240))
    fb = Features(cam.project(pts @ R.T).astype(np.float32), np.zeros((60, 32), np.uint8), "orb", (320, 240))
    idx = np.arange(60, dtype=np.int32)
    v = Verification(Matches(idx, idx, np.zeros(60, np.float32)), np.ones(60, bool), np.eye(3), 1.0, 0.0)
    assert scene_scale(fa, fb, v, cam, cam) == pytest.approx(1.0, abs=1e-6)
    closer = Features(cam.project(pts * np.array([1, 1, 0.5])).astype(np.float32), fa.descriptors, "orb", (320, 240))
    assert scene_scale(closer, fa, v, cam, cam) > 1.5  # half the depth: the scene about twice as large


def test_scene_scale_needs_enough_inliers(pair):
    a, b, _ = pair
    fa, fb = extract(a, FeatureConfig()), extract(b, FeatureConfig())
    v = verify(fa, fb)
    cam = CameraIntrinsics(fx=300.0, fy=300.0, cx=a.shape[1] / 2, cy=a.shape[0] / 2)
    few = Verification(v.matches, v.inlier_mask & (np.cumsum(v.inlier_mask) <= 5), v.F, v.similarity, v.flow_px)
    assert np.isnan(scene_scale(fa, fb, few, cam, cam))
