"""Descriptor matching with the right norm, epipolar (RANSAC) verification and a similarity score.

``match_descriptors`` keeps nearest neighbours that pass Lowe's ratio test and, optionally, are
mutual. ``match_descriptors_grouped`` does the same among descriptors of the same group only (the
vocabulary-tree node they fall under, as ORB-SLAM's bag-of-words guided matching): ~1/G of the
distance evaluations for G groups, which is what makes verifying a shortlist cheap. ``verify`` fits
a fundamental matrix with OpenCV's USAC (MAGSAC or PROSAC) and counts inliers: the number of
*verified matches* is what keyframing, loop closure and localization decide on.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from topomap.camera import CameraIntrinsics
from topomap.config import MatchConfig
from topomap.errors import ConfigError
from topomap.features import Features, hamming

__all__ = ["Matches", "Verification", "match_descriptors", "match_descriptors_grouped", "verify", "scene_scale",
           "MIN_MODEL_POINTS"]

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
    def verified(self) -> bool:
        """The images verified: at least ``min_inliers`` epipolar inliers (:func:`verify` keeps none otherwise)."""
        return self.F is not None

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
    return _one_to_one(ia_arr, ib_arr, dist_arr)


def _one_to_one(ia: np.ndarray, ib: np.ndarray, dist: np.ndarray) -> Matches:
    """One A keypoint per B keypoint (the closest), so inlier counts are not inflated."""
    order = np.lexsort((ia, dist))
    _, first = np.unique(ib[order], return_index=True)
    keep = np.sort(order[first])
    return Matches(ia[keep], ib[keep], dist[keep])


def _pair_distances(da: np.ndarray, db: np.ndarray, binary: bool) -> np.ndarray:
    """Row-wise distances of two equally long (P, D) descriptor arrays -> (P,) float32."""
    if binary:
        return hamming(da, db).astype(np.float32)
    diff = da.astype(np.float32) - db.astype(np.float32)
    return np.sqrt(np.einsum("pd,pd->p", diff, diff))


def _segment_best_two(d: np.ndarray, seg_of: np.ndarray, starts: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per segment (pairs ``starts[s]:starts[s+1]`` of row ``seg_of``): best distance, its pair index
    and the second-best distance (inf where a segment has one pair, nan-free); rows without pairs get inf."""
    best = np.full(n, np.inf, np.float32)
    second = np.full(n, np.inf, np.float32)
    arg = np.full(n, -1, np.int64)
    if len(d) == 0:
        return best, arg, second
    rows = seg_of[starts]
    b = np.minimum.reduceat(d, starts)
    best[rows] = b
    hit = np.flatnonzero(d == np.repeat(b, np.diff(np.append(starts, len(d)))))
    first = hit[np.concatenate(([True], seg_of[hit][1:] != seg_of[hit][:-1]))]  # first minimum of each segment
    arg[seg_of[first]] = first
    d2 = d.copy()
    d2[first] = np.inf
    second[rows] = np.minimum.reduceat(d2, starts)
    return best, arg, second


def match_descriptors_grouped(a: Features, b: Features, groups_a: np.ndarray, groups_b: np.ndarray,
                              config: MatchConfig = MatchConfig(), max_distance: float | None = None) -> Matches:
    """Ratio-test (and optionally mutual) nearest neighbours, searched only among descriptors of the
    same group (``groups_a`` (Na,), ``groups_b`` (Nb,) non-negative ints, e.g. vocabulary-tree
    nodes). ``max_distance`` also bounds the best distance (a group may hold a single candidate, where
    the ratio test cannot judge). Vectorised over all same-group pairs: written here because OpenCV's
    matchers have no grouping and a per-group loop in Python costs more than it saves."""
    _check_pair(a, b)
    groups_a, groups_b = np.asarray(groups_a, np.int64), np.asarray(groups_b, np.int64)
    if len(groups_a) != len(a) or len(groups_b) != len(b):
        raise ValueError("one group per descriptor is needed")
    if len(a) < 2 or len(b) < 2:
        return Matches.empty()
    n_groups = int(max(groups_a.max(), groups_b.max())) + 1
    order_b = np.argsort(groups_b, kind="stable")
    count_b = np.bincount(groups_b, minlength=n_groups)
    start_b = np.cumsum(count_b) - count_b
    c = count_b[groups_a]  # candidates of each A row
    total = int(c.sum())
    if total == 0:
        return Matches.empty()
    seg_start = np.cumsum(c) - c  # first pair of each A row
    ia = np.repeat(np.arange(len(a)), c)
    within = np.arange(total) - np.repeat(seg_start, c)
    ib = order_b[np.repeat(start_b[groups_a], c) + within]
    d = _pair_distances(a.descriptors[ia], b.descriptors[ib], a.detector.binary)
    nonempty = np.flatnonzero(c > 0)
    best, arg, second = _segment_best_two(d, ia, seg_start[nonempty], len(a))
    ok = np.isfinite(best) & (best < config.ratio * second)
    if max_distance is not None:
        ok &= best <= max_distance
    rows_a = np.flatnonzero(ok)
    if len(rows_a) == 0:
        return Matches.empty()
    pair = arg[rows_a]
    ia_arr, ib_arr, dist_arr = ia[pair].astype(np.int32), ib[pair].astype(np.int32), best[rows_a]
    if config.mutual:
        # the B descriptor's nearest A descriptor (among its group, i.e. the same pairs) must be this one
        best_b = np.full(len(b), np.inf, np.float32)
        np.minimum.at(best_b, ib, d)
        keep = dist_arr <= best_b[ib_arr]
        ia_arr, ib_arr, dist_arr = ia_arr[keep], ib_arr[keep], dist_arr[keep]
    return _one_to_one(ia_arr, ib_arr, dist_arr)


_USAC = {"magsac": cv2.USAC_MAGSAC, "prosac": cv2.USAC_PROSAC}


def _fundamental(pa: np.ndarray, pb: np.ndarray, config: MatchConfig) -> tuple[np.ndarray | None, np.ndarray | None]:
    """USAC fundamental matrix (``config.ransac_method``; PROSAC expects the rows best match first);
    plain RANSAC where USAC trips over degenerate data."""
    cv2.setRNGSeed(config.seed)
    try:
        return cv2.findFundamentalMat(
            pa, pb, _USAC[config.ransac_method], config.ransac_px, config.ransac_confidence, config.ransac_max_iters
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
    if config.ransac_method == "prosac":  # PROSAC samples the best-ranked matches first
        matches = matches.subset(np.argsort(matches.distance, kind="stable"))
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


#: Inliers at least this far [rad] from the inliers' mean direction take part in :func:`scene_scale`
#: (closer ones make the ratio noise; 0.02 rad is ~5 px at the working resolution).
SCALE_MIN_ANGLE_RAD = 0.02


def scene_scale(a: Features, b: Features, v: Verification, camera_a: CameraIntrinsics, camera_b: CameraIntrinsics
                ) -> float:
    """How much larger image A shows the verified scene than image B: the median, over the inliers, of
    their angle from the inliers' mean viewing direction in A over that in B. Above 1 the camera of A
    is closer to what both see (along the view: what the epipolar inliers alone cannot tell); angles
    between rays do not change when a camera turns, so a rotation leaves it at 1 (pixel distances
    would stretch toward the image's edges). NaN with fewer than 8 usable inliers."""
    m = v.inlier_matches
    if len(m) < MIN_MODEL_POINTS:
        return float("nan")
    ba, bb = camera_a.rays(a.keypoints[m.ia]), camera_b.rays(b.keypoints[m.ib])
    ra, rb = (np.arccos(np.clip(r @ (r.sum(axis=0) / np.linalg.norm(r.sum(axis=0))), -1.0, 1.0)) for r in (ba, bb))
    ok = rb > SCALE_MIN_ANGLE_RAD
    return float(np.median(ra[ok] / rb[ok])) if np.count_nonzero(ok) >= MIN_MODEL_POINTS else float("nan")
