"""Linking a new experience to the map's others by sequence alignment (``topomap build --append``).

A traversal appended to a map under other conditions (night, winter) is linked to the first
experience by verified loop closures where features match. Where only appearance does — an
appearance-only map, or features that die in the dark — the keyframes of the new experience are run,
in their order and in reverse, through the sequence filter (:class:`~topomap.localize.SequenceLocalizer`)
over the map's *other* experiences, and each keyframe whose filtered answer reaches
``BuildConfig.align_min_confidence`` in either pass is linked to the node answered (by the more
confident pass): SeqSLAM's idea — a sequence of frames is recognised where a single one is not —
with the filter's probability as the criterion.

Links are kept apart from the edges (:meth:`TopoMap.aligned_links`): they say "same place" to
localization, not "servo from here to there" to the planner — nothing verified the geometry.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from topomap.calibration import Calibration, image_quality, quality_reference
from topomap.config import LocalizeConfig
from topomap.graph import TopoMap
from topomap.localize import Localizer, Query, SequenceLocalizer
from topomap.self_supervision import keyframe_image

__all__ = ["align_experience", "QUALITY_SAMPLE"]

log = logging.getLogger(__name__)

#: Keyframes of the earlier experiences whose median image quality is the filter's reference.
QUALITY_SAMPLE = 60


def align_experience(tmap: TopoMap, new_ids: list[int], min_confidence: float,
                     config: LocalizeConfig | None = None, seed: int = 0,
                     on_progress: Callable[[int, int], None] | None = None) -> list[tuple[int, int, float]]:
    """Aligned links ``(new node, earlier node, confidence)`` from the keyframes ``new_ids`` (one
    experience, in build order) to the map's other nodes; the map itself is not changed.
    ``on_progress(done, total)`` after each keyframe of the two passes.

    A keyframe already joined to another experience by an edge (a verified loop closure) gets no
    link. Without keyframe images (maps built with ``--no-images``) nothing is aligned."""
    new = set(int(n) for n in new_ids)
    if not new or len(new) == len(tmap.nodes):
        return []
    if any(tmap.nodes[n].image is None and tmap.nodes[n].image_data is None for n in new):
        log.warning("the appended keyframes carry no images (--no-images): not aligned by appearance")
        return []
    loc = Localizer(tmap, config or LocalizeConfig())
    loc.quality_reference = _quality_reference(tmap, new, seed)
    joined = {a for e in tmap.edges.values() for a, b in ((e.a, e.b), (e.b, e.a))
              if a in new and b not in new}
    # the filter run forward and backward over the run: each pass knows the frames on one side of a
    # keyframe (the build has the whole run, so a keyframe at the start need not go unlinked)
    order = sorted(new)
    exclude = loc.rows_of(order)
    best: dict[int, tuple[float, int]] = {}
    done = 0
    for run in (order, order[::-1]):
        filt = SequenceLocalizer(loc)
        for nid in run:  # images decoded as they come: memory does not grow with the run
            r = filt.update_query(_node_query(loc, tmap, nid, keyframe_image(tmap, nid)), exclude_rows=exclude)
            if r.node not in new and r.confidence > best.get(nid, (-1.0, -1))[0]:
                best[nid] = (float(r.confidence), int(r.node))
            done += 1
            if on_progress is not None:
                on_progress(done, 2 * len(order))
    return [(nid, old, conf) for nid, (conf, old) in sorted(best.items())
            if conf >= min_confidence and nid not in joined]


def _node_query(loc: Localizer, tmap: TopoMap, node_id: int, image: np.ndarray) -> Query:
    """A keyframe of the map as a query: its stored features and descriptors (what ``prepare`` would
    compute from the undecoded image; the stored JPEG has lost detail), the decoded image for quality."""
    node = tmap.nodes[node_id]
    g = None
    if loc.use_hog:
        g = loc.global_descriptors.matrix[loc.rows_of([node_id])[0]]
    words = tmap.index.words_of_features(node_id) if tmap.index is not None else None
    desc = node.descriptor if loc.use_thumbnail else np.zeros(0, np.float32)
    vocabulary = loc._vocabulary if words is not None else None
    return Query(image, node.features, desc, words, vocabulary, g, image_quality(image))


def _quality_reference(tmap: TopoMap, new: set[int], seed: int) -> dict:
    """The earlier experiences' keyframe quality (the calibration's reference when the map has one):
    the new keyframes are judged against it, so that a night run's flat frames say less."""
    cal = Calibration.from_meta(tmap.meta)
    if cal is not None and cal.reference:
        return dict(cal.reference)
    old = np.array(sorted(n for n in tmap.nodes if n not in new), np.int64)
    pick = np.random.default_rng(seed).choice(old, size=min(QUALITY_SAMPLE, len(old)), replace=False)
    return quality_reference([image_quality(img) for n in sorted(pick.tolist())
                              if (img := keyframe_image(tmap, n)) is not None])
