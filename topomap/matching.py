"""Descriptor matching with the right norm, epipolar (RANSAC) verification and a similarity score.

``match_descriptors`` keeps nearest neighbours that pass Lowe's ratio test and, optionally, are
mutual. ``verify`` fits a fundamental matrix with OpenCV's USAC/MAGSAC and counts inliers: the
number of *verified matches* is what keyframing, loop closure and localization decide on.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from topomap.config import MatchConfig
from topomap.errors import ConfigError
from topomap.features import Features

__all__ = ["Matches", "Verification", "match_descriptors", "verify", "MIN_MODEL_POINTS"]

#: Correspondences the fundamental-matrix estimator needs.
MIN_MODEL_POINTS = 8


@dataclass(frozen=True)
class Matches:
    """Tentative correspondences: ``ia`` (M,) int32 rows of A, ``ib`` (M,) int32 rows of B,
    ``distance`` (M,) float32 descriptor distances."""

    ia: np.ndarray
    ib: np.ndarray
    distance: np.ndarray

    def __len__(self) -> int:
        return len(self.ia)

    @classmethod
    def empty(cls) -> Matches:
        return cls(np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros(0, np.float32))

    def subset(self, mask: np.ndarray) -> Matches:
        return Matches(self.ia[mask], self.ib[mask], self.distance[mask])


@dataclass(frozen=True)
class Verification:
    """Result of geometric verification between images A and B.

    ``matches``: the tentative matches; ``inlier_mask``: (M,) bool, epipolar inliers;
    ``F``: (3, 3) float64 fundamental matrix (``x_b^T F x_a = 0``) or ``None``;
    ``similarity``: verified matches / features of the smaller image, in [0, 1];
    ``flow_px``: median image displacement of the inliers at the working resolution [px].
    """

    matches: Matches
    inlier_mask: np.ndarray
    F: np.ndarray | None
    similarity: float
    flow_px: float

    @property
    def inliers(self) -> int:
        return int(self.inlier_mask.sum())

    @property
    def inlier_ratio(self) -> float:
        return self.inliers / len(self.matches) if len(self.matches) else 0.0

    @property
    def inlier_matches(self) -> Matches:
        return self.matches.subset(self.inlier_mask)


def _check_pair(a: Features, b: Features) -> None:
    if a.kind != b.kind:
        raise ConfigError(
            f"cannot match {a.kind} features against {b.kind} features; use the feature type the map was built with"
        )


def match_descriptors(a: Features, b: Features, config: MatchConfig = MatchConfig()) -> Matches:
    """Ratio-test (and optionally mutual) nearest-neighbour matches from A to B."""
    _check_pair(a, b)
    if len(a) < 2 or len(b) < 2:
        return Matches.empty()
    norm = a.detector.norm
    bf = cv2.BFMatcher(norm)
    knn = bf.knnMatch(a.descriptors, b.descriptors, k=2)
    ia, ib, dist = [], [], []
    for pair in knn:
        if len(pair) < 2:
            continue
        m, n = pair
        if m.distance < config.ratio * n.distance:
            ia.append(m.queryIdx)
            ib.append(m.trainIdx)
            dist.append(m.distance)
    if not ia:
        return Matches.empty()
    ia_arr, ib_arr = np.array(ia, np.int32), np.array(ib, np.int32)
    dist_arr = np.array(dist, np.float32)
    if config.mutual:
        # best A-neighbour of each matched B descriptor must point back
        back = bf.match(b.descriptors[ib_arr], a.descriptors)
        back_idx = np.array([m.trainIdx for m in back], np.int32)
        keep = back_idx == ia_arr
        ia_arr, ib_arr, dist_arr = ia_arr[keep], ib_arr[keep], dist_arr[keep]
    # one A keypoint per B keypoint (the closest), so inlier counts are not inflated
    order = np.lexsort((ia_arr, dist_arr))
    _, first = np.unique(ib_arr[order], return_index=True)
    keep = np.sort(order[first])
    return Matches(ia_arr[keep], ib_arr[keep], dist_arr[keep])


def _fundamental(pa: np.ndarray, pb: np.ndarray, config: MatchConfig) -> tuple[np.ndarray | None, np.ndarray | None]:
    """MAGSAC fundamental matrix; plain RANSAC where USAC trips over degenerate data."""
    cv2.setRNGSeed(config.seed)
    try:
        return cv2.findFundamentalMat(
            pa, pb, cv2.USAC_MAGSAC, config.ransac_px, config.ransac_confidence, config.ransac_max_iters
        )
    except cv2.error:
        # OpenCV 4.x USAC can fail an internal assertion on near-degenerate samples
        cv2.setRNGSeed(config.seed)
        try:
            return cv2.findFundamentalMat(pa, pb, cv2.FM_RANSAC, config.ransac_px, config.ransac_confidence, config.ransac_max_iters)
        except cv2.error:
            return None, None


def verify(a: Features, b: Features, config: MatchConfig = MatchConfig(), matches: Matches | None = None) -> Verification:
    """Match A to B (unless ``matches`` is given) and keep the epipolar inliers (USAC MAGSAC, seeded)."""
    if matches is None:
        matches = match_descriptors(a, b, config)
    none = np.zeros(len(matches), bool)
    if len(matches) < max(MIN_MODEL_POINTS, config.min_inliers):
        return Verification(matches, none, None, 0.0, 0.0)
    pa = a.keypoints[matches.ia].astype(np.float64)
    pb = b.keypoints[matches.ib].astype(np.float64)
    F, mask = _fundamental(pa, pb, config)
    if F is None or mask is None or F.shape != (3, 3):
        return Verification(matches, none, None, 0.0, 0.0)
    inl = mask.ravel().astype(bool)
    n = int(inl.sum())
    if n < config.min_inliers:
        return Verification(matches, none, None, 0.0, 0.0)
    similarity = n / max(1, min(len(a), len(b)))
    flow = float(np.median(np.linalg.norm(pa[inl] - pb[inl], axis=1)))
    return Verification(matches, inl, F, float(similarity), flow)
