"""topomap.features: the detector registry (norms, dtypes) and extract()."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from map_synth import sequence

from topomap.config import FeatureConfig
from topomap.errors import ConfigError
from topomap.features import DETECTORS, Features, detector, extract


@pytest.fixture(scope="module")
def frame():
    return sequence(1)[0]


def test_registry_norms_and_dtypes():
    assert set(DETECTORS) == {"orb", "sift", "akaze"}
    assert detector("orb").norm == cv2.NORM_HAMMING and detector("orb").binary
    assert detector("akaze").norm == cv2.NORM_HAMMING and detector("akaze").binary
    assert detector("sift").norm == cv2.NORM_L2 and not detector("sift").binary
    assert detector("sift").dtype is np.float32 and detector("orb").dtype is np.uint8
    assert detector("ORB") is DETECTORS["orb"]  # case-insensitive


def test_unknown_kind_lists_choices():
    with pytest.raises(ConfigError, match="unknown feature type 'surf'; choose one of: akaze, orb, sift"):
        detector("surf")
    with pytest.raises(ConfigError, match="akaze, orb, sift"):
        extract(np.zeros((64, 64), np.uint8), FeatureConfig(kind="brisk"))


@pytest.mark.parametrize("kind", ["orb", "sift", "akaze"])
def test_extract_shapes_dtypes_and_cap(frame, kind):
    det = detector(kind)
    f = extract(frame, FeatureConfig(kind=kind, max_features=300))
    assert 100 <= len(f) <= 300  # the textured scene has plenty; the cap holds (AKAZE has none of its own)
    assert f.keypoints.shape == (len(f), 2) and f.keypoints.dtype == np.float32
    assert f.descriptors.shape == (len(f), det.descriptor_size) and f.descriptors.dtype == det.dtype
    assert f.kind == kind and f.image_size == (frame.shape[1], frame.shape[0])
    h, w = frame.shape
    assert (f.keypoints >= 0).all() and (f.keypoints[:, 0] < w).all() and (f.keypoints[:, 1] < h).all()


def test_extract_is_deterministic_and_keeps_the_strongest(frame):
    a = extract(frame, FeatureConfig(max_features=500))
    b = extract(frame, FeatureConfig(max_features=500))
    np.testing.assert_array_equal(a.keypoints, b.keypoints)
    np.testing.assert_array_equal(a.descriptors, b.descriptors)
    # AKAZE detects the same points whatever the cap, so a smaller cap keeps a prefix: the strongest
    many = extract(frame, FeatureConfig(kind="akaze", max_features=1000))
    few = extract(frame, FeatureConfig(kind="akaze", max_features=50))
    assert len(many) > 50
    np.testing.assert_array_equal(few.keypoints, many.keypoints[:50])
    np.testing.assert_array_equal(few.descriptors, many.descriptors[:50])


def test_blank_image_gives_empty_features():
    f = extract(np.full((120, 160), 90, np.uint8))
    assert len(f) == 0
    assert f.keypoints.shape == (0, 2) and f.descriptors.shape == (0, 32) and f.descriptors.dtype == np.uint8


def test_extract_rejects_non_grey_u8(frame):
    with pytest.raises(ConfigError, match="uint8"):
        extract(frame.astype(np.float32))
    with pytest.raises(ConfigError, match="uint8"):
        extract(np.dstack([frame] * 3))


def test_features_validates_shapes():
    with pytest.raises(ValueError, match="differ in length"):
        Features(np.zeros((3, 2), np.float32), np.zeros((2, 32), np.uint8), "orb", (10, 10))
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        Features(np.zeros((3, 3), np.float32), np.zeros((3, 32), np.uint8), "orb", (10, 10))
    e = Features.empty("sift", (4, 3))
    assert len(e) == 0 and e.descriptors.shape == (0, 128) and e.descriptors.dtype == np.float32
