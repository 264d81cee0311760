"""Frame -> node: global retrieval, geometric verification, confidence, temporal filtering.

Images only: a :class:`Localizer` receives images and the map (whose keyframes carry their own
camera intrinsics); it never sees a pose.

Scoring. For a query image every node gets an *appearance score*, in robust z-units (median / MAD
across the map's nodes): the bag-of-words cosine similarity and the patch-normalised thumbnail
distance, summed (``descriptor="fused"``; ``"bow"`` or ``"thumbnail"`` use one of them). The
thumbnail distance to each node is first standardised by that node's own distances to the rest of
the map in sequence mode, so a bland image resembling everything (a "hub") does not collect the
belief. The
``shortlist_k`` best nodes are verified geometrically; each verified inlier beyond the chance level
(the matcher's ``min_inliers``) adds ``inlier_weight``. Verification matches descriptors only under
the same vocabulary-tree node (``guided_matching``, ORB-SLAM's bag-of-words search): a few hundred
distance evaluations per feature become a few, with the same recall (see LocalizeConfig).
A softmax of the scores (sharpness ``beta``) is the probability of being at each node; the
*confidence* of an answer is the probability mass on the answered node and its graph neighbours.
Under ``min_confidence`` the answer is ``unknown``: "not in this map".

Sequences. :class:`SequenceLocalizer` is a discrete Bayes filter whose states are (node, speed):
the position along the chain of nodes of a map sequence and a speed in nodes per frame (negative:
travelling backwards, zero: standing still). Each frame the belief moves by its speed, speeds drift
to their neighbours with ``speed_change_probability``, a ``graph_hop_probability`` follows any map
edge (loop closures, links between sequences) and a ``jump_probability`` teleports anywhere, so the
filter recovers after a kidnapping. The speed states are what SeqSLAM's trajectory search gets
right: a camera moving through the map keeps moving the same way, and a camera standing still keeps
a stable answer. The observation model is the softmax of the appearance scores; the answered node is
then verified geometrically.
"""

from __future__ import annotations

import dataclasses
import enum
import logging
from collections import OrderedDict
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from topomap.config import LocalizeConfig
from topomap.errors import ConfigError, IndexMissingError, unknown_choice
from topomap.features import Features, extract
from topomap.graph import TopoMap
from topomap.images import to_gray_u8, to_working_resolution
from topomap.matching import Verification, match_descriptors_grouped, verify
from topomap.retrieval import THUMBNAIL_PATCH, THUMBNAIL_SIZE, Vocabulary, sad, thumbnail_descriptor

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

#: Appearance signals a localizer can rank nodes by (``--descriptor``).
DESCRIPTORS = {
    "auto": f"fused when keyframes hold >= {MIN_FEATURES_FOR_BOW} features and the map has an index, else thumbnail",
    "fused": "bag-of-words + patch-normalised thumbnail",
    "bow": "bag-of-words of local features (needs the map's index)",
    "thumbnail": "patch-normalised thumbnail (whole image; works where keypoints fail)",
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
    ``confidence``: probability mass on the node and its neighbours, in [0, 1];
    ``candidates``: the ranking, best first (Recall@N reads it); ``verification``: the geometric
    check against the answered node (inlier matches, usable by a servo), or ``None``.
    """

    node: int
    confidence: float
    status: LocalizationStatus
    inliers: int
    candidates: tuple[Candidate, ...]
    verification: Verification | None = None

    @property
    def localized(self) -> bool:
        return self.status is LocalizationStatus.LOCALIZED


@dataclass(frozen=True)
class Query:
    """A query image prepared for the map: ``image`` (H, W) uint8 at the map's working
    resolution, its local ``features``, whole-image ``descriptor`` (D,) float32 and, when the map
    has a vocabulary, ``words`` (F,) int64: the word of each feature in ``vocabulary`` (a query
    prepared for another map is quantised again, not misread)."""

    image: np.ndarray
    features: Features
    descriptor: np.ndarray
    words: np.ndarray | None = None
    vocabulary: Vocabulary | None = None


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


def _robust_z(x: np.ndarray) -> np.ndarray:
    """(x - median) / (1.4826 MAD), with a floor on the scale so near-constant scores stay ~0."""
    if len(x) == 0:
        return x
    med = float(np.median(x))
    mad = 1.4826 * float(np.median(np.abs(x - med)))
    scale = max(mad, 0.25 * float(np.std(x)), 1e-6)
    return (x - med) / scale


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
            mode = "fused" if (tmap.index is not None and typical >= MIN_FEATURES_FOR_BOW) else "thumbnail"
        if mode in ("fused", "bow") and tmap.index is None:
            raise IndexMissingError(
                "this map has no place-recognition index; build it with `topomap index MAP` "
                "(or use --descriptor thumbnail)"
            )
        self.mode = mode
        self.use_bow = mode in ("fused", "bow")
        self.use_thumbnail = mode in ("fused", "thumbnail")
        if self.use_bow and not np.array_equal(np.sort(tmap.index.node_ids), self.node_ids):
            raise IndexMissingError("the map's index does not cover its nodes; rebuild it with `topomap index MAP`")
        self._bow_rows = np.array([tmap.index.row_of(n) for n in self.node_ids]) if self.use_bow else None
        desc_meta = tmap.meta.get("descriptor") or {}
        self.descriptor_size = tuple(desc_meta.get("size", THUMBNAIL_SIZE))
        self.descriptor_patch = int(desc_meta.get("patch", THUMBNAIL_PATCH))
        if self.use_thumbnail:
            missing = [int(n) for n in self.node_ids if tmap.nodes[int(n)].descriptor is None]
            if missing:
                raise IndexMissingError(f"nodes {missing[:5]} have no whole-image descriptor; rebuild the map")
            self._descriptors = np.stack([tmap.nodes[int(n)].descriptor for n in self.node_ids]).astype(np.float32)
        self._desc_stats: tuple[np.ndarray, np.ndarray] | None = None  # computed on first use (sequence mode)
        self._adjacency = _adjacency(tmap, self.node_ids, self._row)
        # guided matching: groups = vocabulary-tree nodes at the deepest level with <= match_groups nodes
        self._vocabulary = tmap.index.vocabulary if tmap.index is not None else None
        self.guided = self.config.guided_matching and self._vocabulary is not None
        self._group_level = self._vocabulary.group_level(self.config.match_groups) if self.guided else 0
        self._node_words: OrderedDict[int, np.ndarray] = OrderedDict()  # maps indexed without feature words
        self._verify_config = dataclasses.replace(tmap.config.match, ransac_method=self.config.verify_ransac_method,
                                                  ransac_max_iters=self.config.verify_max_iters)

    # ------------------------------------------------------------------ pieces
    def prepare(self, image: np.ndarray, *, words: bool = True) -> Query:
        """Any image (grey/colour, any depth and size) -> :class:`Query` at the map's resolution;
        ``words=False`` skips the vocabulary words (only global localization needs them; a query
        without them is quantised when it is localized)."""
        gray = to_gray_u8(image)
        work = to_working_resolution(gray, self.map.working_size)
        feats = extract(work, self.map.config.features)  # verification needs them in every mode
        desc = thumbnail_descriptor(work, self.descriptor_size, self.descriptor_patch) if self.use_thumbnail else np.zeros(0, np.float32)
        if words and (self.use_bow or self.guided):
            return Query(work, feats, desc, self._vocabulary.quantize(feats.descriptors), self._vocabulary)
        return Query(work, feats, desc)

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
        score = np.zeros(len(self.node_ids))
        if self.use_bow:
            score += _robust_z(self.map.index.scores(q.features, self._query_words(q))[self._bow_rows].astype(np.float64))
        if self.use_thumbnail:
            # fused on a big map: thumbnails only for the bag of words' best nodes (a distance to all
            # of 100k nodes costs ~35 ms); the others get the lowest thumbnail score of those
            rows = None
            if self.use_bow and len(score) > self.config.thumbnail_candidates:
                rows = _top_rows(score, self.config.thumbnail_candidates)
            d = sad(q.descriptor, self._descriptors if rows is None else self._descriptors[rows]).astype(np.float64)
            if hub_correction:
                if self._desc_stats is None:
                    self._desc_stats = _distance_statistics(self._descriptors)
                mu, sd = self._desc_stats
                d = (d - mu) / sd if rows is None else (d - mu[rows]) / sd[rows]
            z = _robust_z(-d)
            if rows is None:
                score += z
            else:
                full = np.full(len(score), z.min())
                full[rows] = z
                score += full
        return score

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
        return float(self.config.guided_max_hamming) if self._vocabulary.binary else None

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

    def total_score(self, q: Query, k: int | None = None) -> tuple[np.ndarray, dict[int, Verification]]:
        """Appearance score plus the inlier bonus of the verified shortlist."""
        score = self.appearance(q)
        checks = self.verify_candidates(q, score, k)
        chance = self.map.config.match.min_inliers  # inliers up to this level occur between unrelated images
        for r, v in checks.items():
            score[r] += self.config.inlier_weight * max(0, v.inliers - chance)
        return score, checks

    def likelihood(self, score: np.ndarray) -> np.ndarray:
        """Observation model: softmax weights ``exp(beta * (score - max))``, (N,)."""
        return np.exp(self.config.beta * (score - score.max()))

    def neighbourhood_mass(self, p: np.ndarray, row: int) -> float:
        """Probability on node ``row`` and its graph neighbours."""
        lo, hi = self._adjacency.indptr[row], self._adjacency.indptr[row + 1]
        return float(p[row] + p[self._adjacency.indices[lo:hi]].sum())

    def answer(self, p: np.ndarray, score: np.ndarray, checks: dict[int, Verification], rank_by: np.ndarray) -> Localization:
        order = _top_rows(rank_by, max(MIN_CANDIDATES, self.config.shortlist_k))
        best = int(order[0])
        conf = min(1.0, self.neighbourhood_mass(p, best))
        cands = tuple(
            Candidate(int(self.node_ids[r]), float(score[r]), checks[r].inliers if r in checks else -1, float(p[r]))
            for r in order[: max(MIN_CANDIDATES, self.config.shortlist_k)]
        )
        status = LocalizationStatus.LOCALIZED if conf >= self.config.min_confidence else LocalizationStatus.UNKNOWN
        v = checks.get(best)
        return Localization(int(self.node_ids[best]), conf, status, v.inliers if v else 0, cands, v)

    # ------------------------------------------------------------------ API
    def localize(self, image: np.ndarray) -> Localization:
        """Global localization of one image (no memory of previous queries)."""
        return self.localize_query(self.prepare(image))

    def localize_query(self, q: Query) -> Localization:
        score, checks = self.total_score(q)
        p = self.likelihood(score)
        p /= p.sum()
        loc = self.answer(p, score, checks, score)
        if loc.status is LocalizationStatus.LOCALIZED and loc.inliers < self.map.config.match.min_inliers:
            # never confidently wrong: one frame whose best node was not verified geometrically (a
            # query too small for features, or no candidate verified) is not a place recognised
            loc = dataclasses.replace(loc, status=LocalizationStatus.UNKNOWN)
        return loc

    def localize_all(self, images: Iterable[np.ndarray]) -> Iterator[Localization]:
        for img in images:
            yield self.localize(img)


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
        n = len(localizer.node_ids)
        steps = int(round(cfg.max_speed_nodes / cfg.speed_step_nodes))
        self.speeds = np.arange(-steps, steps + 1) * cfg.speed_step_nodes  # [nodes/frame]
        self._moves = [_chain_shift(localizer.map, localizer.node_ids, v) for v in self.speeds]
        deg = np.asarray(localizer._adjacency.sum(axis=1)).ravel()
        self._hop = sp.diags(1.0 / np.maximum(deg, 1.0)) @ localizer._adjacency  # row-stochastic
        self._has_edges = deg > 0
        self._state: np.ndarray | None = None  # (N, S) joint belief given that the camera is in the map
        self.belief: np.ndarray | None = None
        self.elsewhere = 0.0
        # appearance-only maps (thumbnail descriptor: keypoints too few to verify) cannot tell
        self._tells_elsewhere = localizer.config.elsewhere_state and localizer.use_bow

    def reset(self) -> None:
        self._state = None
        self.belief = None
        self.elsewhere = 0.0

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

    def update_query(self, q: Query) -> Localization:
        cfg = self.loc.config
        prior, e = self._predict()
        # appearance places the camera within the map (if it is in the map) ...
        score = self.loc.appearance(q, hub_correction=True)
        post = prior * self.loc.likelihood(score)[:, None]
        total = post.sum()
        self._state = post / total if total > 0 and np.isfinite(total) else np.full_like(prior, 1.0 / prior.size)
        belief = self._state.sum(axis=1)
        best = int(np.argmax(belief))
        checks = self.loc.verify_rows(q, [best])
        # ... and geometry tells the map from elsewhere, where keypoints can be trusted to verify
        if self._tells_elsewhere and len(q.features) >= MIN_FEATURES_FOR_BOW and best in checks:
            ok = checks[best].inliers >= self.loc.map.config.match.min_inliers
            in_map = (1.0 - e) * (cfg.verified_in_map if ok else 1.0 - cfg.verified_in_map)
            out = e * (cfg.verified_elsewhere if ok else 1.0 - cfg.verified_elsewhere)
            e = out / (in_map + out)
        self.elsewhere = e
        self.belief = belief * (1.0 - e)
        return self.loc.answer(self.belief, score, checks, self.belief)

    def run(self, images: Iterable[np.ndarray]) -> Iterator[Localization]:
        for img in images:
            yield self.update(img)


# ---------------------------------------------------------------------- graph helpers
def _adjacency(tmap: TopoMap, node_ids: np.ndarray, row: dict[int, int]) -> sp.csr_matrix:
    """Symmetric (N, N) 0/1 adjacency of the map graph in ``node_ids`` order."""
    n = len(node_ids)
    a = [row[e.a] for e in tmap.edges.values() if e.a in row and e.b in row]
    b = [row[e.b] for e in tmap.edges.values() if e.a in row and e.b in row]
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
