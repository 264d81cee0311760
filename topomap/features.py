"""Local features: a registry of detectors, each carrying its descriptor norm, and :func:`extract`.

``DETECTORS`` is a plain dict ``{"orb": ..., "sift": ..., "akaze": ...}``. Binary descriptors (ORB,
AKAZE) are compared with the Hamming norm, float ones (SIFT) with L2 — the registry says which, so
matching never has to guess.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from topomap.config import FeatureConfig
from topomap.errors import ConfigError, unknown_choice

__all__ = ["Features", "Detector", "DETECTORS", "detector", "extract", "hamming"]


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distances of packed binary descriptors, broadcast over leading axes: (..., B) uint8 x
    (..., B) uint8 -> (...) int32. numpy's popcount on 64-bit words (8x fewer elements than bytes)."""
    a, b = np.ascontiguousarray(a, np.uint8), np.ascontiguousarray(b, np.uint8)
    if not (a.shape[-1] % 8 == 0 and a.shape[-1] > 8):  # e.g. AKAZE's 61 bytes
        return np.bitwise_count(np.bitwise_xor(a, b)).sum(axis=-1, dtype=np.int32)
    counts = np.bitwise_count(np.bitwise_xor(a.view(np.uint64), b.view(np.uint64)))
    total = counts[..., 0].astype(np.int32)
    for i in range(1, counts.shape[-1]):  # a few words: cheaper than sum(axis=-1)
        total += counts[..., i]
    return total


@dataclass(frozen=True)
class Features:
    """Keypoints and descriptors of one image.

    ``keypoints``: (N, 2) float32 pixel coordinates ``(x, y)`` at the working resolution;
    ``descriptors``: (N, D) uint8 for binary kinds (D bytes) or float32 for SIFT (D = 128);
    ``kind``: the detector's registry key; ``image_size``: ``(width, height)`` of the image they
    were extracted from.
    """

    keypoints: np.ndarray
    descriptors: np.ndarray
    kind: str
    image_size: tuple[int, int]

    def __post_init__(self) -> None:
        if self.keypoints.ndim != 2 or self.keypoints.shape[1] != 2:
            raise ValueError(f"keypoints must be (N, 2), got {self.keypoints.shape}")
        if len(self.keypoints) != len(self.descriptors):
            raise ValueError("keypoints and descriptors differ in length")

    def __len__(self) -> int:
        return len(self.keypoints)

    @property
    def detector(self) -> Detector:
        return detector(self.kind)

    @classmethod
    def empty(cls, kind: str, image_size: tuple[int, int]) -> Features:
        det = detector(kind)
        return cls(
            np.zeros((0, 2), np.float32), np.zeros((0, det.descriptor_size), det.dtype), kind, tuple(image_size)
        )


@dataclass(frozen=True)
class Detector:
    """A registry entry: how to build the OpenCV detector and how its descriptors compare."""

    name: str
    norm: int  # cv2.NORM_HAMMING (binary) or cv2.NORM_L2 (float)
    dtype: type  # descriptor element type
    descriptor_size: int  # bytes (binary) or floats per descriptor
    make: Callable[[FeatureConfig], cv2.Feature2D]

    @property
    def binary(self) -> bool:
        return self.norm == cv2.NORM_HAMMING


def _orb(cfg: FeatureConfig) -> cv2.Feature2D:
    return cv2.ORB_create(nfeatures=cfg.max_features, scaleFactor=1.2, nlevels=8, fastThreshold=cfg.fast_threshold)


def _sift(cfg: FeatureConfig) -> cv2.Feature2D:
    return cv2.SIFT_create(nfeatures=cfg.max_features)


def _akaze(cfg: FeatureConfig) -> cv2.Feature2D:
    return cv2.AKAZE_create(threshold=0.0008)


DETECTORS: dict[str, Detector] = {
    "orb": Detector("orb", cv2.NORM_HAMMING, np.uint8, 32, _orb),
    "sift": Detector("sift", cv2.NORM_L2, np.float32, 128, _sift),
    "akaze": Detector("akaze", cv2.NORM_HAMMING, np.uint8, 61, _akaze),  # no count limit of its own: extract() caps it
}


def detector(kind: str) -> Detector:
    """The registry entry for ``kind``; an unknown kind lists the valid ones."""
    try:
        return DETECTORS[str(kind).lower()]
    except KeyError:
        raise unknown_choice("feature type", kind, DETECTORS) from None


def extract(image: np.ndarray, config: FeatureConfig = FeatureConfig()) -> Features:
    """Detect and describe keypoints in a ``(H, W) uint8`` image at its given resolution.

    At most ``config.max_features`` keypoints are kept, the strongest first (ties broken by
    position, so the result is deterministic).
    """
    if image.ndim != 2 or image.dtype != np.uint8:
        raise ConfigError(f"extract() needs a (H, W) uint8 image, got {image.shape} {image.dtype}")
    det = detector(config.kind)
    h, w = image.shape
    kps, desc = det.make(config).detectAndCompute(image, None)
    if desc is None or len(kps) == 0:
        return Features.empty(det.name, (w, h))
    xy = np.array([k.pt for k in kps], dtype=np.float32).reshape(-1, 2)
    response = np.array([k.response for k in kps], dtype=np.float32)
    # strongest first; lexsort's last key is primary
    order = np.lexsort((xy[:, 0], xy[:, 1], -response))
    if len(order) > config.max_features:
        order = order[: config.max_features]
    return Features(np.ascontiguousarray(xy[order]), np.ascontiguousarray(desc[order].astype(det.dtype)), det.name, (w, h))
