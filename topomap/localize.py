"""Frame -> node: global retrieval, geometric verification, confidence, temporal filtering.

Images only: a :class:`Localizer` receives images and the map (whose keyframes carry their own
camera intrinsics); it never sees a pose.

Scoring. For a query image every node gets an *appearance score*, in robust z-units (median / MAD
across the map's nodes): the bag-of-words cosine similarity, the whole-image HOG similarity and the
patch-normalised thumbnail distance, summed (``descriptor="fused"``; ``"bow"``, ``"hog"`` or
``"thumbnail"`` use one of them). The thumbnail distance to each node is first standardised by that
node's own distances to the rest of the map in sequence mode, so a bland image resembling
everything (a "hub") does not collect the belief. The ``shortlist_k`` best nodes are verified geometrically; each verified inlier beyond the chance level
(the matcher's ``min_inliers``) adds ``inlier_weight``. Verification matches descriptors only under
the same vocabulary-tree node (``guided_matching``, ORB-SLAM's bag-of-words search): a few hundred
distance evaluations per feature become a few, with the same recall (see LocalizeConfig).
A softmax of the scores (sharpness ``beta``) puts a probability mass on the answered node and its
graph neighbours; on a calibrated map (:mod:`topomap.calibration`) the *confidence* is instead the
calibrated probability that the answer is right. Under ``min_confidence`` the answer is ``unknown``;
a single frame is declared only when its answer verifies geometrically.

Sequences. :class:`SequenceLocalizer` is a discrete Bayes filter whose states are (node, speed):
the position along the chain of nodes of a map sequence and a speed in nodes per frame (negative:
travelling backwards, zero: standing still). Each frame the belief moves by its speed, speeds drift
to their neighbours with ``speed_change_probability``, a ``graph_hop_probability`` follows any map
edge (loop closures, links between sequences) and a ``jump_probability`` teleports anywhere, so the
filter recovers after a kidnapping. The speed states are what SeqSLAM's trajectory search gets
right: a camera moving through the map keeps moving the same way, and a camera standing still keeps
a stable answer. The observation model is the softmax of the appearance scores, flattened on noisy,
flat or clipped frames, whose scores are also judged against each node's own recent scores
(:class:`RecentScores`: a node matching every dark frame tells nothing); a virtual "elsewhere" state, updated by geometric verification (keypoint
maps) or by the filter's predictive likelihood (appearance-only maps), says "not in this map".
"""

from __future__ import annotations

import dataclasses
import enum
import logging
import math
from collections import OrderedDict, deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from topomap.calibration import Calibration, ImageQuality, image_quality, logit, quality_evidence
from topomap.config import LocalizeConfig
from topomap.errors import ConfigError, IndexMissingError, unknown_choice
from topomap.features import Features, detector, extract
from topomap.graph import TopoMap
from topomap.images import to_gray_u8, to_working_resolution
from topomap.matching import Verification, match_descriptors_grouped, verify
from topomap.retrieval import (
    THUMBNAIL_PATCH,
    THUMBNAIL_SIZE,
    GlobalDescriptors,
    Vocabulary,
    hog_descriptor,
    make_thumbnail,
    sad,
    thumbnail_descriptor,
)

__all__ = [
    "DESCRIPTORS",
    "LocalizationStatus",
    "Candidate",
    "Localization",
    "Query",
    "Localizer",
    "SequenceLocalizer",
]

log = logging.getLogger(__name__)

#: ``descriptor="auto"`` uses the keypoint index only when keyframes typically hold this many
#: features: fewer words than this make a bag of words noise (Nordland 64x32: ~26 per image).
MIN_FEATURES_FOR_BOW = 100
#: Nodes whose vocabulary words are kept quantised (maps indexed before words were stored) [nodes].
WORD_CACHE_NODES = 4096
#: A localization lists at least this many candidates, whatever the verified shortlist's size.
MIN_CANDIDATES = 10
#: The descriptor length ``LocalizeConfig.guided_max_hamming`` is given for (ORB's); longer ones scale it.
ORB_DESCRIPTOR_BITS = 256
#: An experience of fewer nodes is standardised with the whole map (a median of a few scores says little).
MIN_EXPERIENCE_NODES = 16

#: Appearance signals a localizer can rank nodes by (``--descriptor``).
DESCRIPTORS = {
    "auto": f"fused when keyframes hold >= {MIN_FEATURES_FOR_BOW} features and the map has an index, else hog",
    "fused": "bag-of-words + gradient orientations (HOG) + patch-normalised thumbnail",
    "bow": "bag-of-words of local features (needs the map's index)",
    "hog": "whole-image gradient orientations (survive light and season changes; works where keypoints fail); "
           "on frames noisier or darker than the map's keyframes the thumbnail is blended in",
    "thumbnail": "patch-normalised thumbnail (SeqSLAM's whole-image descriptor)",
}


class LocalizationStatus(str, enum.Enum):
    LOCALIZED = "localized"
    UNKNOWN = "unknown"  # confidence under the threshold: probably not in this map


@dataclass(frozen=True)
class Candidate:
    """A ranked node: its total ``score`` (appearance z-score + inlier bonus), verified ``inliers``
    (-1 when not verified) and posterior ``probability``."""

    node: int
    score: float
    inliers: int
    probability: float


@dataclass(frozen=True)
class Localization:
    """Answer for one query image.

    ``node``: best node (also given when ``status`` is ``unknown``, as the best guess);
    ``confidence``: in [0, 1], the calibrated probability that ``node`` is right on a calibrated map,
    else the probability mass on the node and its neighbours;
    ``candidates``: the ranking, best first (Recall@N reads it); ``verification``: the geometric
    check against the answered node (inlier matches, usable by a servo), or ``None``;
    ``calibrated``: whether ``confidence`` is the map's calibrated probability that ``node`` is
    right (else the raw softmax mass, which ranks answers but overstates them);
    ``evidence``: the numbers the confidence was computed from (:mod:`topomap.calibration`);
    ``experience``: the build run (sequence) the answered node belongs to; ``place``: the shared
    place it stands for across experiences (:meth:`~topomap.graph.TopoMap.place_ids`).
    """

    node: int
    confidence: float
    status: LocalizationStatus
    inliers: int
    candidates: tuple[Candidate, ...]
    verification: Verification | None = None
    calibrated: bool = False
    evidence: dict = field(default_factory=dict, compare=False)
    experience: int = 0
    place: int = -1

    @property
    def localized(self) -> bool:
        return self.status is LocalizationStatus.LOCALIZED


@dataclass(frozen=True)
class Query:
    """A query image prepared for the map: ``image`` (H, W) uint8 at the map's working
    resolution, its local ``features``, whole-image ``descriptor`` (D,) float32 and, when the map
    has a vocabulary, ``words`` (F,) int64: the word of each feature in ``vocabulary`` (a query
    prepared for another map is quantised again, not misread); ``global_descriptor`` (G,) float32:
    the HOG of its thumbnail (empty when the localizer does not use it)."""

    image: np.ndarray
    features: Features
    descriptor: np.ndarray
    words: np.ndarray | None = None
    vocabulary: Vocabulary | None = None
    global_descriptor: np.ndarray | None = None
    quality: ImageQuality | None = None


def _top_rows(x: np.ndarray, m: int) -> np.ndarray:
    """``np.argsort(-x, kind="stable")[:m]`` without sorting all of ``x``: the ``m`` largest, ties in
    index order. A full sort of 100k scores costs ~8 ms per query; a partition plus a sort of the
    few rows at or above the m-th value costs well under 1 ms."""
    n = len(x)
    m = min(max(int(m), 0), n)
    if m == 0:
        return np.zeros(0, np.intp)
    if n <= 1024:
        return np.argsort(-x, kind="stable")[:m]
    threshold = np.partition(x, n - m)[n - m]  # the m-th largest value
    rows = np.flatnonzero(x >= threshold)  # all rows reaching it (ties included), index order
    return rows[np.argsort(-x[rows], kind="stable")[:m]]


def _spread(z: np.ndarray, rows: np.ndarray, n: int) -> np.ndarray:
    """Scores of ``rows`` placed in an (n,) vector whose other entries get the lowest of them."""
    full = np.full(n, z.min() if len(z) else 0.0)
    full[rows] = z
    return full


def _robust_z(x: np.ndarray) -> np.ndarray:
    """(x - median) / (1.4826 MAD), with a floor on the scale so near-constant scores stay ~0."""
    if len(x) == 0:
        return x
    return (x - float(np.median(x))) / _robust_scale(x)


def _robust_scale(x: np.ndarray) -> float:
    """1.4826 MAD of ``x``, floored at a quarter of its standard deviation (and 1e-6)."""
    med = float(np.median(x))
    return max(1.4826 * float(np.median(np.abs(x - med))), 0.25 * float(np.std(x)), 1e-6)


def _experience_groups(labels: np.ndarray | None) -> list[np.ndarray] | None:
    """Rows of each label (experience) of at least :data:`MIN_EXPERIENCE_NODES` rows, for :func:`_robust_z_by`."""
    if labels is None:
        return None
    groups = (np.flatnonzero(labels == g) for g in np.unique(labels))
    return [rows for rows in groups if len(rows) >= MIN_EXPERIENCE_NODES]


def _robust_z_by(x: np.ndarray, groups: list[np.ndarray] | None) -> np.ndarray:
    """:func:`_robust_z` with each of ``groups`` (rows of one experience, :func:`_experience_groups`)
    centred on its own median, on the whole of ``x``'s scale: an experience's offset is removed (its
    conditions), its spread kept (a tight group scaled on its own would turn small differences into
    large z)."""
    if not groups:
        return _robust_z(x)
    scale = _robust_scale(x)
    z = (x - float(np.median(x))) / scale
    for rows in groups:
        z[rows] = (x[rows] - float(np.median(x[rows]))) / scale
    return z


class Localizer:
    """Single-frame localization against one map; reusable across queries (state-free)."""

    def __init__(self, tmap: TopoMap, config: LocalizeConfig | None = None, *, features_of: Callable[[int], Features] | None = None):
        self.map = tmap
        self.config = config or LocalizeConfig()
        if self.config.descriptor not in DESCRIPTORS:
            raise unknown_choice("descriptor", self.config.descriptor, DESCRIPTORS)
        self.node_ids = np.array(sorted(tmap.nodes), np.int64)
        if len(self.node_ids) == 0:
            raise ConfigError("the map has no nodes")
        self._row = {int(n): i for i, n in enumerate(self.node_ids)}
        self._features_of = features_of or (lambda n: tmap.nodes[n].features)
        mode = self.config.descriptor
        if mode == "auto":
            typical = float(np.median([len(n.features) for n in tmap.nodes.values()]))
            mode = "fused" if (tmap.index is not None and typical >= MIN_FEATURES_FOR_BOW) else "hog"
        if mode in ("fused", "bow") and tmap.index is None:
            raise IndexMissingError(
                "this map has no place-recognition index; build it with `topomap index MAP` "
                "(or use --descriptor hog)"
            )
        self.mode = mode
        self.use_bow = mode in ("fused", "bow")
        self.use_thumbnail = mode in ("fused", "thumbnail")
        self.use_hog = mode in ("fused", "hog")
        self.global_descriptors = _global_descriptors(tmap, self.node_ids) if self.use_hog else None
        if self.use_bow and not np.array_equal(np.sort(tmap.index.node_ids), self.node_ids):
            raise IndexMissingError("the map's index does not cover its nodes; rebuild it with `topomap index MAP`")
        self._bow_rows = np.array([tmap.index.row_of(n) for n in self.node_ids]) if self.use_bow else None
        desc_meta = tmap.meta.get("descriptor") or {}
        self.descriptor_size = tuple(desc_meta.get("size", THUMBNAIL_SIZE))
        self.descriptor_patch = int(desc_meta.get("patch", THUMBNAIL_PATCH))
        missing = ([int(n) for n in self.node_ids if tmap.nodes[int(n)].descriptor is None]
                   if self.use_thumbnail or mode == "hog" else [])
        if self.use_thumbnail and missing:
            raise IndexMissingError(f"nodes {missing[:5]} have no whole-image descriptor; rebuild the map")
        # HOG's gradients drown in the noise of a dark frame where the patch-normalised thumbnail (SeqSLAM's
        # descriptor) survives: on such frames the filter blends it in by the frame's degradation
        self.blend_thumbnail = mode == "hog" and not missing
        if self.use_thumbnail or self.blend_thumbnail:
            self._descriptors = np.stack([tmap.nodes[int(n)].descriptor for n in self.node_ids]).astype(np.float32)
        self._desc_stats: tuple[np.ndarray, np.ndarray] | None = None  # computed on first use (sequence mode)
        self._adjacency = _adjacency(tmap, self.node_ids, self._row)
        self._place = tmap.place_ids()
        # each experience's scores are standardised on their own: a query taken under one experience's
        # conditions resembles all of that experience's nodes a little (light, camera, season), which
        # would otherwise outscore the right place of another (docs/localization.md, Experiences)
        seqs = np.array([tmap.nodes[int(n)].sequence for n in self.node_ids])
        counts = np.unique(seqs, return_counts=True)[1]
        self._experience_labels = seqs if int((counts >= MIN_EXPERIENCE_NODES).sum()) >= 2 else None
        self._experience_rows = _experience_groups(self._experience_labels)  # once, not per query
        # guided matching: groups = vocabulary-tree nodes at the deepest level with <= match_groups nodes
        self._vocabulary = tmap.index.vocabulary if tmap.index is not None else None
        self.guided = self.config.guided_matching and self._vocabulary is not None
        self._group_level = self._vocabulary.group_level(self.config.match_groups) if self.guided else 0
        self._node_words: OrderedDict[int, np.ndarray] = OrderedDict()  # maps indexed without feature words
        self._verify_config = dataclasses.replace(tmap.config.match, ransac_method=self.config.verify_ransac_method,
                                                  ransac_max_iters=self.config.verify_max_iters)
        stored = Calibration.from_meta(tmap.meta)
        self.calibration = self._usable_calibration(stored) if self.config.use_calibration else None
        # the keyframes' image quality a query's is judged against: a property of the map, whatever
        # scoring the calibration was fitted for (without it, night frames would count as clean)
        self.quality_reference: dict = (dict(stored.reference) if stored is not None
                                        and stored.fitted_for.get("nodes") == len(self.node_ids) else {})

    # ------------------------------------------------------------------ pieces
    def prepare(self, image: np.ndarray, *, words: bool = True) -> Query:
        """Any image (grey/colour, any depth and size) -> :class:`Query` at the map's resolution;
        ``words=False`` skips the vocabulary words (only global localization needs them; a query
        without them is quantised when it is localized)."""
        gray = to_gray_u8(image)
        work = to_working_resolution(gray, self.map.working_size)
        feats = extract(work, self.map.config.features)  # verification needs them in every mode
        desc = (thumbnail_descriptor(work, self.descriptor_size, self.descriptor_patch)
                if self.use_thumbnail or self.blend_thumbnail else np.zeros(0, np.float32))
        g = None
        if self.use_hog:  # from the query's thumbnail, exactly as the nodes' were made at build time
            g = hog_descriptor(make_thumbnail(work, self.map.config.thumbnail_px), self.global_descriptors.size)
        if words and (self.use_bow or self.guided):
            return Query(work, feats, desc, self._vocabulary.quantize(feats.descriptors), self._vocabulary, g,
                         image_quality(work))
        return Query(work, feats, desc, global_descriptor=g, quality=image_quality(work))

    def _query_words(self, q: Query) -> np.ndarray:
        """The query features' words in this map's vocabulary (computed by ``prepare``, else now)."""
        if q.vocabulary is self._vocabulary and q.words is not None and len(q.words) == len(q.features):
            return q.words
        return self._vocabulary.quantize(q.features.descriptors)

    def appearance(self, q: Query, hub_correction: bool = False) -> np.ndarray:
        """Appearance score of every node, (N,) float64 in ``node_ids`` order (robust z-units).

        ``hub_correction`` standardises each node's thumbnail distance by that node's distances to
        the rest of the map. It pays off where evidence accumulates over frames (a bland node that
        scores well on every frame would otherwise collect belief: corridor sequence Recall@1 0.79
        -> 0.86, Nordland 0.62 -> 0.68) but costs single frames (corridor 0.62 -> 0.52), so the
        sequence filter uses it and single-frame queries do not.
        """
        plain, hubbed = self._appearances(q, hub_correction)
        return hubbed if hub_correction else plain

    def _appearances(self, q: Query, hub_correction: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """The appearance score without and (``hub_correction``) with the thumbnails' hub correction:
        the bag of words and HOG are computed once for both (the sequence filter needs both)."""
        score = np.zeros(len(self.node_ids))
        if self.use_bow:
            bow = self.map.index.scores(q.features, self._query_words(q), self.config.bow_max_postings)
            score += _robust_z_by(bow[self._bow_rows].astype(np.float64), self._experience_rows)
        # fused on a big map: whole-image descriptors only for the bag of words' best nodes (a
        # thumbnail distance to all of 100k nodes costs ~35 ms); the others get the lowest score of those
        rows = None
        if self.use_bow and len(score) > self.config.thumbnail_candidates:
            rows = _top_rows(score, self.config.thumbnail_candidates)
        if self.use_hog:
            g = q.global_descriptor
            if g is None or len(g) != self.global_descriptors.matrix.shape[1]:
                g = hog_descriptor(make_thumbnail(q.image, self.map.config.thumbnail_px), self.global_descriptors.size)
            # no hub correction here: standardising by each node's own similarities costs the
            # corridor's sequence mode (see docs/localization.md)
            z = _robust_z_by(self.global_descriptors.similarity(g, rows).astype(np.float64), self._groups_of(rows))
            score += z if rows is None else _spread(z, rows, len(score))
        # hog: on a degraded frame the sequence filter's scores blend the thumbnail in (standardised per
        # node it carries sequences where HOG dies; a single frame keeps HOG: unstandardised, the
        # thumbnail is the weaker single-frame descriptor, docs/localization.md)
        w = self.degradation(q) if self.blend_thumbnail and hub_correction else 0.0
        if not self.use_thumbnail and w == 0.0:
            return score, (score.copy() if hub_correction else None)
        desc = q.descriptor
        if len(desc) != self._descriptors.shape[1]:  # prepared by a localizer that did not need it
            desc = thumbnail_descriptor(q.image, self.descriptor_size, self.descriptor_patch)
        d = sad(desc, self._descriptors if rows is None else self._descriptors[rows]).astype(np.float64)
        hub = None
        if hub_correction:
            if self._desc_stats is None:
                self._desc_stats = _distance_statistics(self._descriptors)
            mu, sd = self._desc_stats
            z = _robust_z_by(-((d - mu) / sd if rows is None else (d - mu[rows]) / sd[rows]), self._groups_of(rows))
            hub = z if rows is None else _spread(z, rows, len(score))
        if not self.use_thumbnail:  # hog, the thumbnail weighted in by the frame's degradation
            return score, (1.0 - w) * score + w * hub
        z = _robust_z_by(-d, self._groups_of(rows))
        plain = score + (z if rows is None else _spread(z, rows, len(score)))
        return plain, (None if hub is None else score + hub)

    def _groups_of(self, rows: np.ndarray | None) -> list[np.ndarray] | None:
        """Experience groups among ``rows`` (all rows when ``None``) for :func:`_robust_z_by`."""
        if self._experience_labels is None or rows is None:
            return self._experience_rows
        return _experience_groups(self._experience_labels[rows])

    def degradation(self, q: Query) -> float:
        """How much worse the frame is than the map's keyframes, in [0, 1): ``1 - 1 / (1 + low_snr +
        contrast_loss + clipping)`` against :attr:`quality_reference` (0: like the keyframes)."""
        ev = quality_evidence(q.quality or image_quality(q.image), self.quality_reference)
        return 1.0 - 1.0 / (1.0 + ev["low_snr"] + ev["contrast_loss"] + ev["clipping"])

    def verify_candidates(self, q: Query, score: np.ndarray, k: int | None = None) -> dict[int, Verification]:
        """Geometric verification of the ``k`` best-scoring nodes: ``{row: Verification}``."""
        k = self.config.shortlist_k if k is None else k
        return self.verify_rows(q, _top_rows(score, k))

    def verify_rows(self, q: Query, rows: Iterable[int]) -> dict[int, Verification]:
        """Geometric verification of the query against the given node rows."""
        if len(q.features) < self.map.config.match.min_inliers:
            return {}
        out = {}
        cfg = self._verify_config
        q_groups = None
        if self.guided:
            q_groups = self._vocabulary.ancestors(self._query_words(q), self._group_level)
        for r in rows:
            node = int(self.node_ids[r])
            f = self._features_of(node)
            if len(f) < cfg.min_inliers:
                continue
            matches = None
            if q_groups is not None:
                groups = self._vocabulary.ancestors(self._words_of_node(node, f), self._group_level)
                matches = match_descriptors_grouped(q.features, f, q_groups, groups, cfg, self._max_distance)
            out[int(r)] = verify(q.features, f, cfg, matches=matches)
        return out

    @property
    def _max_distance(self) -> float | None:
        """The guided matches' Hamming cap in this map's descriptor bits: ``guided_max_hamming`` is
        given for ORB's 256 bits and scales with the length (AKAZE's 488-bit MLDB: 114), the same
        share of differing bits; SIFT (not binary) has none."""
        if not self._vocabulary.binary:
            return None
        bits = 8 * detector(self._vocabulary.kind).descriptor_size
        return self.config.guided_max_hamming * bits / ORB_DESCRIPTOR_BITS

    def _words_of_node(self, node: int, f: Features) -> np.ndarray:
        """The vocabulary word of each feature of ``node``: from the index (stored at indexing time),
        else quantised now and kept in a bounded cache (maps indexed before words were stored)."""
        words = self.map.index.words_of_features(node) if self.map.index is not None else None
        if words is not None and len(words) == len(f):
            return words
        cached = self._node_words.get(node)
        if cached is None or len(cached) != len(f):
            cached = self._node_words[node] = self._vocabulary.quantize(f.descriptors)
            if len(self._node_words) > WORD_CACHE_NODES:
                self._node_words.popitem(last=False)
        else:
            self._node_words.move_to_end(node)
        return cached

    def total_score(self, q: Query, k: int | None = None, exclude: np.ndarray | None = None,
                    appearance: np.ndarray | None = None) -> tuple[np.ndarray, dict[int, Verification]]:
        """Appearance score (``appearance`` when already computed) plus the inlier bonus of the
        verified shortlist; rows in ``exclude`` score ``-inf`` (self-supervised calibration leaves a
        keyframe out of its own query)."""
        score = self.appearance(q) if appearance is None else appearance.copy()
        if exclude is not None and len(exclude):
            score[exclude] = -np.inf
        checks = self.verify_candidates(q, score, k)
        chance = self.map.config.match.min_inliers  # inliers up to this level occur between unrelated images
        for r, v in checks.items():
            score[r] += self.config.inlier_weight * max(0, v.inliers - chance)
        return score, checks

    def likelihood(self, score: np.ndarray, beta: float | None = None) -> np.ndarray:
        """Observation model: softmax weights ``exp(beta * (score - max))``, (N,); excluded rows 0."""
        beta = self.config.beta if beta is None else beta
        top = np.max(score)
        return np.exp(beta * (score - top)) if np.isfinite(top) else np.ones_like(score)

    def neighbourhood_mass(self, p: np.ndarray, row: int) -> float:
        """Probability on node ``row`` and its graph neighbours."""
        return float(p[row] + p[self.neighbour_rows(row)].sum())

    def neighbour_rows(self, row: int) -> np.ndarray:
        lo, hi = self._adjacency.indptr[row], self._adjacency.indptr[row + 1]
        return self._adjacency.indices[lo:hi]

    def evidence(self, q: Query, score: np.ndarray, best: int, mass: float, checks: dict[int, Verification]) -> dict:
        """What the answer ``best`` rests on (:data:`topomap.calibration.SINGLE_FEATURES`): the margin of
        its score over the best node outside its neighbourhood [z-units], log(1 + verified inliers),
        the log-odds of its probability mass, and the query image's quality against the keyframes'."""
        near = np.zeros(len(score), bool)
        near[best] = True
        near[self.neighbour_rows(best)] = True
        outside = score[~near]
        outside = outside[np.isfinite(outside)]
        margin = float(score[best] - outside.max()) if len(outside) else 10.0
        v = checks.get(best)
        ev = {"margin": float(np.clip(margin, -10.0, 10.0)), "log_inliers": math.log1p(max(0, v.inliers) if v else 0),
              "log_odds": logit(mass)}
        ev.update(quality_evidence(q.quality or image_quality(q.image), self.quality_reference))
        return ev

    def answer(self, p: np.ndarray, score: np.ndarray, checks: dict[int, Verification], rank_by: np.ndarray,
               confidence: Callable[[int, float], tuple[float, bool, dict]] | None = None) -> Localization:
        """The ranking's best node with its confidence: ``confidence(best_row, mass)`` -> (value,
        calibrated, evidence) when given, else the raw probability mass on the node and its neighbours."""
        n_cands = max(MIN_CANDIDATES, self.config.shortlist_k)
        order = _top_rows(rank_by, n_cands)
        best = int(order[0])
        mass = min(1.0, self.neighbourhood_mass(p, best))
        conf, calibrated, ev = (mass, False, {}) if confidence is None else confidence(best, mass)
        cands = tuple(
            Candidate(int(self.node_ids[r]), float(score[r]), checks[r].inliers if r in checks else -1, float(p[r]))
            for r in order[:n_cands]
        )
        status = LocalizationStatus.LOCALIZED if conf >= self.config.min_confidence else LocalizationStatus.UNKNOWN
        v = checks.get(best)
        node = int(self.node_ids[best])
        return Localization(node, conf, status, v.inliers if v else 0, cands, v, calibrated, ev,
                            self.map.nodes[node].sequence, self._place.get(node, node))

    # ------------------------------------------------------------------ API
    def localize(self, image: np.ndarray) -> Localization:
        """Global localization of one image (no memory of previous queries)."""
        return self.localize_query(self.prepare(image))

    def localize_query(self, q: Query, exclude: Iterable[int] = ()) -> Localization:
        """Localization of a prepared query; node ids in ``exclude`` are never answered."""
        loc, _ = self._single_frame(q, self.rows_of(exclude))
        v = loc.verification
        if loc.localized and not (v is not None and v.verified and v.inliers >= self.config.declare_min_inliers):
            # never confidently wrong: one frame whose answer did not verify geometrically is not a
            # place recognised, however probable its appearance makes it (measured: a calibrated
            # appearance-only answer declared a corridor frame to be in the Nordland map at 0.97),
            # nor one verified only at the level a look-alike place reaches by chance; on maps
            # without the keypoints to verify, the sequence filter is what can declare
            loc = dataclasses.replace(loc, status=LocalizationStatus.UNKNOWN)
        return loc

    def rows_of(self, node_ids: Iterable[int]) -> np.ndarray:
        """Rows (positions in ``node_ids``) of the given node ids that are in the map."""
        return np.array([self._row[int(n)] for n in node_ids if int(n) in self._row], np.intp)

    def _single_frame(self, q: Query, exclude: np.ndarray, appearance: np.ndarray | None = None
                      ) -> tuple[Localization, dict[int, Verification]]:
        """The frame on its own — its answer with its evidence and (calibrated map) probability,
        before the verification rule of :meth:`localize_query` — and the shortlist's verifications."""
        score, checks = self.total_score(q, exclude=exclude, appearance=appearance)
        p = self.likelihood(score)
        p /= p.sum()

        def confidence(best: int, mass: float) -> tuple[float, bool, dict]:
            ev = self.evidence(q, score, best, mass, checks)
            if self.calibration is None:
                return mass, False, ev
            return self.calibration.single.probability(ev), True, ev

        return self.answer(p, score, checks, score, confidence), checks

    def _usable_calibration(self, cal: Calibration | None) -> Calibration | None:
        """The map's calibration when it was fitted for this map and this scoring, else ``None``."""
        if cal is None:
            return None
        fitted = cal.fitted_for
        if fitted.get("descriptor") != self.mode or fitted.get("nodes") != len(self.node_ids):
            log.warning("the map's calibration was fitted for another map or descriptor; confidences are raw "
                        "(refit with `topomap index MAP`)")
            return None
        return cal


#: Frames of history before a node's recent scores count as its bias (the mean of fewer is noise).
RECENT_MIN_FRAMES = 3


class RecentScores:
    """Each node's appearance scores over the last ``frames`` frames, as running sums (O(N) a frame).

    Under a change the map never saw (night, a noisy or mis-exposed camera) some nodes score high
    against *every* frame — a dark keyframe against dark frames, a bland one against noise — and a
    filter that multiplies the frames' likelihoods parks its belief there. Such a node's high score
    says nothing about where the camera is; what does is how a node scores now *compared with its
    own recent scores*: SeqSLAM's local contrast enhancement, taken along time instead of along
    the reference sequence (which needs the frames to lie along it).
    """

    def __init__(self, frames: int, min_spread: float):
        self.frames = int(frames)
        self.min_spread = float(min_spread)
        self._past: deque[np.ndarray] = deque()
        self._sum: np.ndarray | None = None
        self._sq: np.ndarray | None = None

    def clear(self) -> None:
        self._past.clear()
        self._sum = self._sq = None

    def contrast(self, score: np.ndarray) -> np.ndarray | None:
        """(N,) robust z-scores of ``(score - recent mean) / max(recent spread, min_spread)``, or
        ``None`` while fewer than :data:`RECENT_MIN_FRAMES` frames are known."""
        n = len(self._past)
        if n < RECENT_MIN_FRAMES or self._sum is None or len(score) != len(self._sum):
            return None
        mu = self._sum / n
        sd = np.sqrt(np.maximum(self._sq / n - mu * mu, 0.0))
        return _robust_z((score - mu) / np.maximum(sd, self.min_spread))

    def debias(self, score: np.ndarray, weight: float) -> np.ndarray:
        """``score`` blended with its :meth:`contrast` by ``weight`` in [0, 1]; the frame then joins
        the history."""
        c = self.contrast(score) if weight > 0 else None
        if c is None:
            out = score
        else:
            # a blend of two partly correlated scores can spread less than either: it is stretched
            # back to the score's own spread, so that it does not flatten the likelihood (flattening
            # a degraded frame is beta's job, not the blend's)
            out = (1.0 - weight) * score + weight * c
            fin = np.isfinite(out)
            if fin.sum() > 2:
                out = out * max(1.0, _robust_scale(score[fin]) / _robust_scale(out[fin]))
        self.push(score)
        return out

    def push(self, score: np.ndarray) -> None:
        if self.frames <= 0 or not np.all(np.isfinite(score)):
            return
        x = np.asarray(score, np.float64).copy()
        if self._sum is None or len(x) != len(self._sum):
            self.clear()
            self._sum, self._sq = np.zeros_like(x), np.zeros_like(x)
        if len(self._past) == self.frames:
            old = self._past.popleft()
            self._sum -= old
            self._sq -= old * old
        self._past.append(x)
        self._sum += x
        self._sq += x * x


class SequenceLocalizer:
    """Bayes filter over (node, speed) states for frames arriving in order.

    ``update(image)`` returns the filtered :class:`Localization`; ``reset()`` forgets the past.
    ``belief`` is the current (N,) probability of each node (speeds summed out); ``elsewhere`` the
    probability that the camera is in no place of this map (a virtual place, see
    :class:`~topomap.config.LocalizeConfig`): ``belief.sum() + elsewhere == 1``.
    """

    def __init__(self, localizer: Localizer):
        self.loc = localizer
        cfg = localizer.config
        steps = int(round(cfg.max_speed_nodes / cfg.speed_step_nodes))
        self.speeds = np.arange(-steps, steps + 1) * cfg.speed_step_nodes  # [nodes/frame]
        self._moves = [_chain_shift(localizer.map, localizer.node_ids, v) for v in self.speeds]
        deg = np.asarray(localizer._adjacency.sum(axis=1)).ravel()
        self._hop = sp.diags(1.0 / np.maximum(deg, 1.0)) @ localizer._adjacency  # row-stochastic
        self._has_edges = deg > 0
        self._state: np.ndarray | None = None  # (N, S) joint belief given that the camera is in the map
        self.belief: np.ndarray | None = None
        self.elsewhere = 0.0
        # "elsewhere" needs evidence that differs between mapped and unmapped frames: geometric
        # verification where keyframes carry the features for it, else whether the frames follow the
        # map's topology (the filter's predictive likelihood, see update_query)
        self._tells_elsewhere = localizer.config.elsewhere_state
        self.frame: Localization | None = None  # the last frame's single-frame answer
        self._recent = RecentScores(cfg.recent_frames, cfg.recent_min_spread)

    def reset(self) -> None:
        self._state = None
        self.belief = None
        self.elsewhere = 0.0
        self._recent.clear()

    def _predict(self) -> tuple[np.ndarray, float]:
        """Prior of the next frame: (N, S) belief over the map's states given that the camera is in
        the map, and the probability that it is elsewhere."""
        cfg = self.loc.config
        n, k = len(self.loc.node_ids), len(self.speeds)
        if self._state is None:  # uniform, and the stationary split of the map <-> elsewhere chain
            e = cfg.leave_probability / (cfg.leave_probability + cfg.enter_probability)
            return np.full((n, k), 1.0 / (n * k)), e if self._tells_elsewhere else 0.0
        e = self.elsewhere
        e += cfg.leave_probability * (1.0 - e) - cfg.enter_probability * e if self._tells_elsewhere else 0.0
        return self._move(self._state), e

    def _move(self, b: np.ndarray) -> np.ndarray:
        """The motion model applied to a map belief (N, S) of any total; returns one of total 1."""
        cfg = self.loc.config
        n, k = len(self.loc.node_ids), len(self.speeds)
        p_hop = np.where(self._has_edges, cfg.graph_hop_probability, 0.0)[:, None]
        on_chain = b * (1.0 - p_hop)
        moved = np.stack([m @ on_chain[:, i] for i, m in enumerate(self._moves)], axis=1)
        moved += self._hop.T @ (b * p_hop)  # along graph edges, keeping the speed
        pc = cfg.speed_change_probability
        drift = (1.0 - pc) * moved
        drift[:, 1:] += 0.5 * pc * moved[:, :-1]
        drift[:, :-1] += 0.5 * pc * moved[:, 1:]
        total = drift.sum()
        drift = drift / total if total > 0 else np.full((n, k), 1.0 / (n * k))
        return (1.0 - cfg.jump_probability) * drift + cfg.jump_probability / (n * k)

    def update(self, image: np.ndarray) -> Localization:
        return self.update_query(self.loc.prepare(image))

    def update_query(self, q: Query, exclude: Iterable[int] = (), *, exclude_rows: np.ndarray | None = None
                     ) -> Localization:
        """Filter one prepared frame; node ids in ``exclude`` (or rows in ``exclude_rows``, for a long
        run excluding the same many nodes) get no observation weight (calibration, alignment)."""
        loc, cfg = self.loc, self.loc.config
        ex = loc.rows_of(exclude) if exclude_rows is None else np.asarray(exclude_rows, np.intp)
        plain, score = loc._appearances(q, hub_correction=True)
        # the frame on its own: its evidence, and (calibrated maps) the probability that it is right
        self.frame, checks = loc._single_frame(q, ex, plain)
        ev1 = self.frame.evidence
        prior, e = self._predict()
        # appearance places the camera within the map (if it is in the map); a noisy or flat frame
        # (night, fog) says less, so its likelihood is flattened instead of pushing belief anywhere
        # (contrast lost and pixels clipped count too: an over-exposed frame keeps its noise level and
        # contrast but loses the texture of its bright half; docs/localization.md has the figures)
        reliability = 1.0 - loc.degradation(q)
        # ... and the more degraded, the more each node is judged against its own recent scores
        # (and at least by recent_min_weight: a node that matches every frame says little on a clean one too)
        obs = self._recent.debias(score, max(cfg.recent_min_weight, 1.0 - reliability))  # score itself, or a new array
        if len(ex):
            score[ex] = -np.inf
            obs[ex] = -np.inf
        lik = loc.likelihood(obs, cfg.beta * reliability)
        post = prior * lik[:, None]
        total = post.sum()
        self._state = post / total if total > 0 and np.isfinite(total) else np.full_like(prior, 1.0 / prior.size)
        belief = self._state.sum(axis=1)
        best = int(np.argmax(belief))
        if best not in checks:
            checks.update(loc.verify_rows(q, [best]))
        # ... and evidence that differs between mapped and unmapped frames tells the map from elsewhere
        ratio = None  # P(frame | in the map, the frames before) / P(frame | elsewhere)
        if not loc.use_bow:
            # appearance-only maps: a camera in the map sees next what the motion model predicts;
            # elsewhere its frames resemble a random place. The Bayes factor of the two is the
            # prior-weighted likelihood over the mean likelihood (1 when the prior says nothing)
            ratio = float(np.clip(prior.sum(axis=1) @ lik / max(lik.mean(), 1e-300), 1.0 / cfg.max_frame_ratio,
                                  cfg.max_frame_ratio))
        elif len(q.features) >= MIN_FEATURES_FOR_BOW and best in checks:
            v = checks[best]
            r_in, r_out = cfg.verified_in_map, cfg.verified_elsewhere
            if not v.verified:
                ratio = (1.0 - r_in) / (1.0 - r_out)
            elif v.inliers >= cfg.elsewhere_min_inliers:
                ratio = r_in / r_out
            # else: a verification at the level chance alignments of a look-alike place reach says nothing
        if self._tells_elsewhere and ratio is not None:
            e = e / (e + (1.0 - e) * ratio)
        self.elsewhere = e
        self.belief = belief * (1.0 - e)

        calibrated = loc.calibration is not None
        frame_ev = {**ev1, "frame_probability": self.frame.confidence if calibrated else None, "elsewhere": e,
                    "frame_ratio": ratio}

        seq_model = loc.calibration.sequence if calibrated else None

        def confidence(row: int, mass: float) -> tuple[float, bool, dict]:
            ev = {**frame_ev, "belief": mass}
            if seq_model is None:  # the filter's posterior
                return mass, calibrated, ev
            # a labelled calibration maps the posterior to the frequency of being right
            return seq_model.probability(sequence_evidence(mass, e)), True, ev

        out = loc.answer(self.belief, score, checks, self.belief, confidence)
        if out.localized and not loc.use_bow and ratio < cfg.declare_min_frame_ratio:
            # a frame that does not itself favour the map declares nothing, whatever the belief carried
            out = dataclasses.replace(out, status=LocalizationStatus.UNKNOWN)
        return out

    def run(self, images: Iterable[np.ndarray]) -> Iterator[Localization]:
        for img in images:
            yield self.update(img)


def sequence_evidence(mass: float, elsewhere: float) -> dict[str, float]:
    """What a sequence answer is judged by (:data:`topomap.calibration.SEQUENCE_FEATURES`): the
    log-odds of the belief mass on the answer and of the filter's probability of being elsewhere."""
    return {"belief_log_odds": logit(mass), "elsewhere_log_odds": logit(elsewhere)}


# ---------------------------------------------------------------------- graph helpers
def _adjacency(tmap: TopoMap, node_ids: np.ndarray, row: dict[int, int]) -> sp.csr_matrix:
    """Symmetric (N, N) 0/1 adjacency of the map graph in ``node_ids`` order, aligned links included
    (one place in two experiences: the filter moves across them, the answer's mass counts both)."""
    n = len(node_ids)
    pairs = [(e.a, e.b) for e in tmap.edges.values()] + [(x, y) for x, y, _ in tmap.aligned_links()]
    a = [row[x] for x, y in pairs if x in row and y in row]
    b = [row[y] for x, y in pairs if x in row and y in row]
    m = sp.coo_matrix((np.ones(len(a)), (a, b)), shape=(n, n))
    m = ((m + m.T) > 0).astype(np.float64).tocsr()
    m.setdiag(0)
    m.eliminate_zeros()
    return m


def _chain_shift(tmap: TopoMap, node_ids: np.ndarray, speed: float) -> sp.csr_matrix:
    """(N, N) matrix moving belief ``speed`` nodes along each sequence's chain (linear interpolation
    between the two nearest nodes); mass pushed past a chain's end is dropped."""
    n = len(node_ids)
    seq = np.array([tmap.nodes[int(i)].sequence for i in node_ids])
    src, dst, w = [], [], []
    for s_id in np.unique(seq):
        rows = np.nonzero(seq == s_id)[0]  # node_ids are sorted, so rows follow build order
        pos = np.arange(len(rows)) + speed
        lo = np.floor(pos).astype(int)
        frac = pos - lo
        for target, weight in ((lo, 1.0 - frac), (lo + 1, frac)):
            ok = (target >= 0) & (target < len(rows)) & (weight > 1e-12)
            src.append(rows[ok])
            dst.append(rows[target[ok]])
            w.append(weight[ok])
    src, dst, w = np.concatenate(src), np.concatenate(dst), np.concatenate(w)
    # new_belief = M @ old_belief: M[dst, src] = w
    return sp.csr_matrix((w, (dst, src)), shape=(n, n))


def _distance_statistics(descriptors: np.ndarray, sample: int = 2000) -> tuple[np.ndarray, np.ndarray]:
    """Mean and spread of each node's thumbnail distance to (a seeded sample of) the other nodes."""
    n = len(descriptors)
    if n < 3:
        return np.zeros(n), np.ones(n)
    rng = np.random.default_rng(0)
    ref = descriptors if n <= sample else descriptors[np.sort(rng.choice(n, sample, replace=False))]
    mu, sd = np.empty(n), np.empty(n)
    for start in range(0, n, 256):  # blocks keep memory at 256 x sample x D
        block = descriptors[start : start + 256]
        d = np.abs(block[:, None, :] - ref[None, :, :]).mean(axis=2)
        d[d < 1e-9] = np.nan  # the node itself
        mu[start : start + len(block)] = np.nanmean(d, axis=1)
        sd[start : start + len(block)] = np.nanstd(d, axis=1)
    sd = np.where(np.isfinite(sd) & (sd > 1e-6), sd, 1.0)
    mu = np.where(np.isfinite(mu), mu, 0.0)
    return mu, sd


def _global_descriptors(tmap: TopoMap, node_ids: np.ndarray) -> GlobalDescriptors:
    """The map's stored HOG descriptors in ``node_ids`` order, else computed now from the thumbnails
    (maps indexed by an older topomap: ~1 ms a node; `topomap index MAP` stores them)."""
    g = GlobalDescriptors.from_map(tmap.arrays, tmap.meta.get("global_descriptor"))
    if g is not None and np.array_equal(g.node_ids, node_ids):
        return g
    log.info("the map stores no whole-image descriptors for its nodes; computing them (`topomap index MAP` keeps them)")
    return GlobalDescriptors.from_thumbnails({int(n): tmap.nodes[int(n)].thumbnail for n in node_ids})

