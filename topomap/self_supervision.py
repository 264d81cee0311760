"""Self-supervised calibration of a map's localization confidence (``topomap index``, ``topomap build``).

The map's own keyframes are queries whose answers are known. Every query is a keyframe image seen
from a little aside (:func:`viewpoint_change`) under a random photometric change
(:func:`topomap.photometric.random_photometric`, from none to about a deep night), in three kinds:

* **nearby** — right when the keyframe's node or a graph neighbour is answered;
* **left out** — its own node excluded, so right only when a neighbour is answered: a live frame
  halfway between two keyframes, the hard case;
* **aliased** — every node within two hops excluded: whatever is answered is a look-alike
  elsewhere in the map, wrong;
* **foreign** — mirrored left-right, another place of the same kind (its node and neighbours
  excluded): every answer is wrong.

On a map of several experiences (``--append``) a fifth kind comes from the traversals themselves:

* **other experience** — a keyframe of one experience, its image as taken, localized against
  another experience alone; right when the answer is where the links between the two experiences
  place it (:func:`experience_labels`). These are real queries of another traversal, the hard
  case no change of a keyframe reproduces.

The samples fit the single-frame model. Its aliased and foreign answers look like the wrong answers
of real queries from another traversal (corridor: margin 2.1 vs 2.4 z-units, log-inliers 2.4 vs 2.7);
its right answers are easier than real ones — what the map's own images cannot show is how hard
the next traversal will be — so the calibration errs on the side of caution (under-confident; see
docs/localization.md). The sequence filter's posterior is a probability by construction and is
not recalibrated by self-supervision (labelled queries can: :func:`calibrate_on_queries`); the
calibration's image-quality reference lets it flatten the likelihood of noisy
and washed-out frames (:class:`~topomap.localize.SequenceLocalizer`).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Collection, Iterable
from dataclasses import dataclass

import cv2
import numpy as np

from topomap.calibration import (CALIBRATION_KEY, POSTERIOR, SEQUENCE_FEATURES, SINGLE_FEATURES, Calibration, Calibrator,
                                  image_quality, quality_reference)
from topomap.config import LocalizeConfig
from topomap.errors import CalibrationError
from topomap.graph import TopoMap
from topomap.images import decode_image
from topomap.localize import Localizer, SequenceLocalizer, sequence_evidence
from topomap.parallel import Executor, worker_local
from topomap.photometric import apply_photometric, random_photometric
from topomap.spill import as_bytes

__all__ = ["calibrate_map", "calibrate_on_queries", "CalibrationSamples", "single_samples", "keyframe_samples", "keyframe_rng", "keyframe_image",
           "viewpoint_change", "experience_labels", "experience_queries", "experience_sample"]

log = logging.getLogger(__name__)

#: Strongest viewpoint change of a nearby query (see :func:`viewpoint_change`): corners moved by up
#: to a quarter of the width.
MAX_VIEW = 3.0
#: An aliased query excludes every node this many graph hops from its own: the answer is then
#: another place of the map that looks alike (the corridor's failure), always wrong.
ALIAS_HOPS = 2
#: Why no calibration could be fitted is reported with this prefix (``topomap info`` shows it).
NOT_CALIBRATED = "not calibrated"
#: An unlinked keyframe of an appended experience is labelled from the nearest linked keyframes
#: before and after it when they are at most this many keyframes apart (a short stretch of one pace).
EXPERIENCE_SPAN = 8
#: Other-experience samples per calibration, at most this many times ``queries`` (a seeded sample).
EXPERIENCE_SAMPLES = 2
#: Maps of more nodes are calibrated in this process even when workers are at hand: each worker would
#: hold a copy of the whole map (~130 KB a node with its localizer), to share ~240 queries that take
#: seconds beside the minutes such a build takes (docs/build.md, "Memory").
PARALLEL_MAX_NODES = 1000


class CalibrationSamples:
    """Evidence rows ``x`` (N, F) over ``features``, labels ``y`` (N,) bool and the sample ``kind``s."""

    def __init__(self, features: tuple[str, ...]):
        self.features = features
        self.rows: list[list[float]] = []
        self.labels: list[bool] = []
        self.kinds: list[str] = []

    def add(self, evidence: dict, right: bool, kind: str) -> None:
        self.rows.append([float(evidence.get(f, 0.0)) for f in self.features])
        self.labels.append(bool(right))
        self.kinds.append(kind)

    @property
    def x(self) -> np.ndarray:
        return np.array(self.rows, np.float64).reshape(len(self.rows), len(self.features))

    @property
    def y(self) -> np.ndarray:
        return np.array(self.labels, bool)

    def __len__(self) -> int:
        return len(self.labels)


def keyframe_image(tmap: TopoMap, node_id: int) -> np.ndarray | None:
    """The keyframe image of ``node_id`` at the working resolution (decoded from the map), or ``None``."""
    n = tmap.nodes[node_id]
    if n.image is not None:
        return n.image
    if n.image_data is not None:
        w, h = tmap.working_size
        return decode_image(as_bytes(n.image_data), max_pixels=w * h, max_size=(w, h), formats=("PNG", "JPEG"),
                            what=f"the image of node {node_id}")
    return None


def viewpoint_change(image: np.ndarray, rng: np.random.Generator, strength: float = 1.0) -> np.ndarray:
    """The image as seen from elsewhere nearby: a random perspective warp whose corners move up to
    ``strength`` x 8 % of the width (and a shift of as much), borders reflected. A live frame between
    two keyframes, or of another traversal, looks like this to a whole-image descriptor and to the
    features; ``strength`` 0 leaves the image as it is."""
    h, w = image.shape[:2]
    s = float(max(strength, 0.0))
    if s == 0.0:
        return image
    src = np.float32([[0, 0], [w, 0], [w, h], [0, h]])
    shift = rng.uniform(-0.08, 0.08, 2) * s * np.array([w, 0.5 * h])
    dst = src + shift + rng.uniform(-0.08, 0.08, (4, 2)) * s * np.array([w, h])
    m = cv2.getPerspectiveTransform(src, dst.astype(np.float32))
    return cv2.warpPerspective(image, m, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def _changed(image: np.ndarray, rng: np.random.Generator, light: float, view: float) -> np.ndarray:
    return apply_photometric(viewpoint_change(image, rng, view), random_photometric(rng, light), rng)


def _overlapping(loc: Localizer) -> bool:
    """Whether neighbouring keyframes show the same place: the build verified its edges with local
    features (keypoint maps), so a left-out keyframe's neighbours are right answers. Appearance-only
    maps (one node per place, edges by order alone) get no left-out samples."""
    return loc.use_bow


def _within_hops(tmap: TopoMap, node_id: int, hops: int) -> set[int]:
    seen, frontier = {node_id}, {node_id}
    for _ in range(hops):
        frontier = {m for n in frontier for m in tmap.linked(n)} - seen
        seen |= frontier
    return seen


def keyframe_rng(seed: int, node_id: int) -> np.random.Generator:
    """The random stream of one keyframe's queries: seeded by the map's seed and the node id, so a
    keyframe's samples are the same whichever worker makes them and whichever others are drawn."""
    return np.random.default_rng((int(seed), int(node_id)))


def keyframe_samples(loc: Localizer, node_id: int, rng: np.random.Generator) -> list[tuple[dict, bool, str]]:
    """The nearby, left-out, aliased and foreign queries of one keyframe (see the module docstring):
    ``(evidence, right, kind)`` each; none when the keyframe has no image or no neighbour."""
    tmap = loc.map
    image = keyframe_image(tmap, node_id)
    neighbours = set(tmap.linked(node_id))  # an aligned twin in another experience is the same place
    if image is None or not neighbours:
        return []
    near = neighbours | {node_id}
    queries = [("nearby", _changed(image, rng, float(rng.random()), float(rng.uniform(0.0, MAX_VIEW))), set(), near)]
    if _overlapping(loc):
        queries.append(("left out", _changed(image, rng, float(rng.random()), 0.3), {node_id}, neighbours))
    queries += [
        ("aliased", _changed(image, rng, float(rng.random()), 0.3), _within_hops(tmap, node_id, ALIAS_HOPS), set()),
        ("foreign", np.ascontiguousarray(_changed(image, rng, float(rng.random()), 0.3)[:, ::-1]), near, set()),
    ]
    out = []
    for kind, img, exclude, right in queries:
        a = loc.localize_query(loc.prepare(img), exclude=exclude)
        out.append((a.evidence, a.node in right, kind))
    return out


def experience_labels(tmap: TopoMap) -> dict[int, tuple[int, tuple[int, ...]]]:
    """Keyframes whose place in another experience is known: node -> (that experience, its nodes
    that are right answers). A keyframe joined to another experience (loop edge or aligned link) is
    at the nodes it is joined to and their neighbours there; one between two joined keyframes at most
    :data:`EXPERIENCE_SPAN` apart, both joined into the same experience at a consistent pace, is where
    the two joins interpolate to, +-1 node. Keyframes outside such stretches are not labelled."""
    seq = {n: node.sequence for n, node in tmap.nodes.items()}
    joins: dict[int, set[int]] = {}
    pairs = [(e.a, e.b) for e in tmap.edges.values()] + [(a, b) for a, b, _ in tmap.aligned_links()]
    for a, b in pairs:
        if a in seq and b in seq and seq[a] != seq[b]:
            joins.setdefault(a, set()).add(b)
            joins.setdefault(b, set()).add(a)
    if not joins:
        return {}
    chains: dict[int, list[int]] = {}
    for n in sorted(seq):  # node ids follow build order within a sequence
        chains.setdefault(seq[n], []).append(n)
    pos = {n: i for chain in chains.values() for i, n in enumerate(chain)}
    nbrs: dict[int, set[int]] = {}
    for a, b in ((e.a, e.b) for e in tmap.edges.values()):
        if seq.get(a) is not None and seq.get(a) == seq.get(b):
            nbrs.setdefault(a, set()).add(b)
            nbrs.setdefault(b, set()).add(a)

    def target(n: int) -> tuple[int, float] | None:
        """The one other experience ``n`` is joined to, and the median chain position there."""
        others = {seq[m] for m in joins.get(n, ())}
        if len(others) != 1:
            return None
        t = others.pop()
        return t, float(np.median([pos[m] for m in joins[n]]))

    out: dict[int, tuple[int, tuple[int, ...]]] = {}
    for s, chain in chains.items():
        anchored = [i for i, n in enumerate(chain) if target(n) is not None]
        for i, n in enumerate(chain):
            tj = target(n)
            if tj is not None:
                right = set(joins[n]) | {m for j in joins[n] for m in nbrs.get(j, ())}
                out[n] = (tj[0], tuple(sorted(right)))
                continue
            k = int(np.searchsorted(anchored, i))
            if k == 0 or k == len(anchored):
                continue
            i0, i1 = anchored[k - 1], anchored[k]
            (t0, j0), (t1, j1) = target(chain[i0]), target(chain[i1])
            # one experience, a pace of at most two of its nodes per keyframe either way
            if t0 != t1 or i1 - i0 > EXPERIENCE_SPAN or abs(j1 - j0) > 2 * (i1 - i0) + 1:
                continue
            j = j0 + (j1 - j0) * (i - i0) / (i1 - i0)
            other = chains[t0]
            lo, hi = max(0, int(np.floor(j)) - 1), min(len(other) - 1, int(np.ceil(j)) + 1)
            out[n] = (t0, tuple(other[lo : hi + 1]))
    return out


def experience_sample(loc: Localizer, node_id: int, label: tuple[int, tuple[int, ...]]) -> tuple[dict, bool, str] | None:
    """The other-experience query of one labelled keyframe (:func:`experience_labels`): its image
    localized against the labelled experience alone; ``None`` when the keyframe has no image."""
    image = keyframe_image(loc.map, node_id)
    if image is None:
        return None
    t, right = label
    exclude = [n for n, node in loc.map.nodes.items() if node.sequence != t]
    a = loc.localize_query(loc.prepare(image), exclude=exclude)
    return a.evidence, a.node in set(right), "other experience"


def experience_queries(tmap: TopoMap, queries: int, seed: int) -> list[tuple[int, tuple[int, tuple[int, ...]]]]:
    """The labelled keyframes the calibration queries (a seeded sample of at most
    :data:`EXPERIENCE_SAMPLES` x ``queries``), with their labels, in node order."""
    labels = experience_labels(tmap)
    with_images = [n for n in sorted(labels) if keyframe_image_stored(tmap, n)]
    cap = EXPERIENCE_SAMPLES * queries
    if len(with_images) > cap:
        rng = np.random.default_rng((int(seed), 1, 0))  # a stream no keyframe_rng draws
        with_images = sorted(rng.choice(with_images, cap, replace=False).tolist())
    return [(int(n), labels[n]) for n in with_images]


def keyframe_image_stored(tmap: TopoMap, node_id: int) -> bool:
    n = tmap.nodes[node_id]
    return n.image is not None or n.image_data is not None


def single_samples(loc: Localizer, node_ids: list[int], seed: int) -> CalibrationSamples:
    """Nearby, left-out, aliased and foreign queries of the given keyframes, each keyframe's drawn
    from :func:`keyframe_rng` (see the module docstring)."""
    out = CalibrationSamples(SINGLE_FEATURES)
    for nid in node_ids:
        for evidence, right, kind in keyframe_samples(loc, nid, keyframe_rng(seed, nid)):
            out.add(evidence, right, kind)
    return out


@dataclass(frozen=True)
class _SamplesTask:
    """One share of the calibration queries: ``node_ids`` of the shared map (``shared``, from
    :meth:`Executor.shared`: the map with the images of the chosen keyframes only), localized with
    ``config`` against the keyframes' ``reference`` quality."""

    config: LocalizeConfig
    reference: dict
    node_ids: tuple[int, ...]
    seed: int
    experience: tuple[tuple[int, tuple[int, tuple[int, ...]]], ...] = ()  # (node, label): experience_queries


def _worker_localizer(shared: tuple, task: _SamplesTask) -> Localizer:
    def make(tmap: TopoMap) -> Localizer:
        loc = Localizer(tmap, task.config)
        loc.quality_reference = task.reference
        return loc

    # one localizer per worker over its one copy of the map, reused by the worker's later shares
    return worker_local(shared, "calibration localizer", make)


def _samples_task(item: tuple[tuple, _SamplesTask]) -> tuple[str, list[tuple[dict, bool, str]], list[tuple[dict, bool, str]]]:
    shared, task = item
    loc = _worker_localizer(shared, task)
    keyframes = [s for nid in task.node_ids for s in keyframe_samples(loc, nid, keyframe_rng(task.seed, nid))]
    return loc.mode, keyframes, [s for nid, label in task.experience if (s := experience_sample(loc, nid, label))]


def _without_images(tmap: TopoMap, keep: set[int]) -> TopoMap:
    """A shallow copy of ``tmap`` for the workers: keyframe images only of ``keep``, no frame records
    (localization reads neither; the images are most of a map's bytes)."""
    nodes = {nid: n if nid in keep else dataclasses.replace(n, image=None, image_data=None) for nid, n in tmap.nodes.items()}
    return dataclasses.replace(tmap, nodes=nodes, frames=[], sequences=[])


def _parallel_samples(tmap: TopoMap, cfg: LocalizeConfig, reference: dict, node_ids: list[int], seed: int,
                      executor: Executor, experience: list = ()) -> tuple[str, CalibrationSamples]:
    """:func:`single_samples` (and the ``experience`` queries) with the keyframes split over
    ``executor``'s workers (a few shares per worker, so one slow worker does not hold up the rest);
    the map goes to each worker once (:meth:`Executor.shared`), the shares carry only node ids. The
    samples come back in keyframe order, with the descriptor mode the workers' localizers chose."""
    n_shares = min(len(node_ids), 2 * executor.workers)
    shares = [tuple(int(n) for n in part) for part in np.array_split(node_ids, n_shares)]
    ex_shares = [tuple(experience[i] for i in idx) for idx in np.array_split(np.arange(len(experience)), n_shares)]
    keep = set(node_ids) | {n for n, _ in experience}
    out, mode, later = CalibrationSamples(SINGLE_FEATURES), "", []
    with executor.shared(_without_images(tmap, keep)) as shared:
        tasks = ((shared, _SamplesTask(cfg, reference, part, seed, ex)) for part, ex in zip(shares, ex_shares) if part or ex)
        for mode, keyframes, other in executor.map(_samples_task, tasks, window=executor.workers):
            for evidence, right, kind in keyframes:
                out.add(evidence, right, kind)
            later += other
    for evidence, right, kind in later:  # after every keyframe sample, as in the serial order
        out.add(evidence, right, kind)
    return mode, out


def calibrate_map(tmap: TopoMap, *, queries: int = 60, seed: int = 0, config: LocalizeConfig | None = None,
                  executor: Executor | None = None) -> Calibration:
    """Fit the map's :class:`~topomap.calibration.Calibration` and store it in ``tmap.meta``.

    ``queries`` keyframes (a seeded sample) give three or four samples each; with ``executor`` their
    queries run on its workers (the same calibration at any worker count) when the map has at most
    :data:`PARALLEL_MAX_NODES` nodes. Raises
    :class:`CalibrationError` when the map has no keyframe images (``--no-images``) or too few nodes
    to learn from.
    """
    cfg = dataclasses.replace(config or LocalizeConfig(), use_calibration=False)
    chosen, reference = _keyframe_reference(tmap, queries, seed)
    experience = experience_queries(tmap, queries, seed)
    if executor is not None and executor.workers > 1 and len(tmap.nodes) <= PARALLEL_MAX_NODES:
        # the workers build the localizers: one here as well would hold a second index of the map
        mode, single = _parallel_samples(tmap, cfg, reference, chosen, seed, executor, experience)
    else:
        loc = Localizer(tmap, cfg)
        # evidence of image quality is relative to the map's keyframes: install the reference first
        loc.quality_reference = reference
        mode, single = loc.mode, single_samples(loc, chosen, seed)
        for nid, label in experience:
            if (sample := experience_sample(loc, nid, label)) is not None:
                single.add(*sample)
    if len(single) < 20 or single.y.all() or not single.y.any():
        raise CalibrationError(f"{NOT_CALIBRATED}: its keyframes gave {len(single)} usable samples, "
                           f"{int(single.y.sum())} of them right; need both right and wrong answers")
    single_model = Calibrator.fit(SINGLE_FEATURES, single.x, single.y)
    kinds = np.array(single.kinds)
    other = kinds == "other experience"
    fitted_for = {"nodes": len(tmap.nodes), "descriptor": mode, "samples": len(single),
                  "right": int(single.y.sum()), "seed": seed,
                  "experience_samples": int(other.sum()), "experience_right": int(single.y[other].sum())}
    cal = Calibration(single_model, reference, fitted_for)
    tmap.meta[CALIBRATION_KEY] = cal.to_dict()
    return cal


def _keyframe_reference(tmap: TopoMap, queries: int, seed: int) -> tuple[list[int], dict]:
    """``queries`` keyframes with images (a seeded sample) and their median image quality, the
    reference a query's quality is judged against."""
    rng = np.random.default_rng(seed)
    with_images = [n for n in sorted(tmap.nodes) if keyframe_image_stored(tmap, n)]
    if len(with_images) < 10:
        raise CalibrationError(f"{NOT_CALIBRATED}: the map needs at least 10 keyframe images to calibrate "
                           f"(it has {len(with_images)}; maps built with --no-images cannot be calibrated)")
    chosen = sorted(rng.choice(with_images, min(queries, len(with_images)), replace=False).tolist())
    return chosen, quality_reference([image_quality(keyframe_image(tmap, n)) for n in chosen])


#: Labelled queries needed to fit a calibration on them (six weights and an intercept).
MIN_LABELLED = 30
#: The sequence calibration is fitted only when the filter answered at least this many of the labelled
#: queries right and as many wrong.
MIN_SEQUENCE_EACH = 10
#: Standard deviation of the prior around the filter's posterior (weight 1, intercept 0).
SEQUENCE_PRIOR_SD = 1.0


def calibrate_on_queries(tmap: TopoMap, queries: Iterable[tuple[np.ndarray, Collection[int]]], *, seed: int = 0,
                         config: LocalizeConfig | None = None) -> Calibration:
    """Fit the map's calibration on **labelled queries** instead of its own views, and store it in
    ``tmap.meta``: ``queries`` yields (image, the node ids that are right for it; empty: a place not
    in the map), e.g. a validation traversal with ground truth (``topomap index MAP --calibrate-on
    QUERIES --ground-truth GT``).

    Self-supervision cannot know how hard the next traversal will be (its right answers are easier
    than a real traversal's: the calibration is cautious); a traversal with ground truth shows it.
    Each query is localized as a single frame with raw confidences, and its evidence, right when the
    answer is among its right nodes, is a sample. Needs :data:`MIN_LABELLED` queries with both right
    and wrong answers among them (raises :class:`CalibrationError`). The queries also pass, in their
    order, through the sequence filter, and mirrored left-right with their right nodes excluded (a
    traversal of a place not in the map: every answer wrong). Where the filter answers at least
    :data:`MIN_SEQUENCE_EACH` of the queries right and as many wrong, its belief mass gets a
    calibration too (``Calibration.sequence``, fitted around the posterior itself); otherwise the
    sequence confidence stays the filter's posterior."""
    cfg = dataclasses.replace(config or LocalizeConfig(), use_calibration=False)
    loc = Localizer(tmap, cfg)
    # the keyframes' quality: the map's stored reference, else measured on its keyframe images
    reference = loc.quality_reference = (loc.quality_reference
                                         or _keyframe_reference(tmap, tmap.config.calibration.queries, seed)[1])
    samples, in_order = CalibrationSamples(SINGLE_FEATURES), CalibrationSamples(SEQUENCE_FEATURES)
    filt, mirrored = SequenceLocalizer(loc), SequenceLocalizer(loc)
    for image, right in queries:
        right = set(right)
        q = loc.prepare(image)
        r = loc.localize_query(q)
        samples.add(r.evidence, r.node in right, "labelled")
        # the same queries, in their order, through the filter ...
        s = filt.update_query(q)
        in_order.add(sequence_evidence(s.confidence, filt.elsewhere), s.node in right, "labelled sequence")
        # ... and mirrored, their places excluded: a traversal of another place of the same kind, so
        # that the fit sees the filter's confidence where the camera is not in the map (always wrong;
        # fitted on mapped frames alone, a foreign traversal got 0.87: docs/localization.md)
        near = {n for m in right if m in tmap.nodes for n in _within_hops(tmap, m, ALIAS_HOPS)}
        s = mirrored.update_query(loc.prepare(np.ascontiguousarray(q.image[:, ::-1])), exclude=near)
        in_order.add(sequence_evidence(s.confidence, mirrored.elsewhere), False, "mirrored sequence")
    n, k = len(samples), int(samples.y.sum())
    if n < MIN_LABELLED or k in (0, n):
        raise CalibrationError(f"{NOT_CALIBRATED}: {n} labelled queries, {k} of them answered right; need at "
                               f"least {MIN_LABELLED} with both right and wrong answers")
    sk = int(in_order.y.sum())  # of the n queries in order (the mirrored ones are all wrong)
    # a posterior's upper end is calibrated only by wrong answers among confident ones: with fewer, the
    # fit would learn the base rate and declare everything (measured: docs/localization.md)
    sequence = (Calibrator.fit(SEQUENCE_FEATURES, in_order.x, in_order.y, around=POSTERIOR, prior_sd=SEQUENCE_PRIOR_SD)
                if min(sk, n - sk) >= MIN_SEQUENCE_EACH else None)
    fitted_for = {"nodes": len(tmap.nodes), "descriptor": loc.mode, "samples": n, "right": k, "seed": seed,
                  "labelled": True, "sequence_right": sk}
    cal = Calibration(Calibrator.fit(SINGLE_FEATURES, samples.x, samples.y), reference, fitted_for, sequence)
    tmap.meta[CALIBRATION_KEY] = cal.to_dict()
    return cal
