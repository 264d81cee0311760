"""Does the current image show a node's keyframe view? The image-side test of arrival at a goal
(docs/theory.md section 4.4): the verified matches barely moved, and the whole image looks more like
the keyframe than its neighbours do — or, where neighbouring keyframes look much alike, more than any
place away from the goal. Facing a single wall the planar relative pose is ambiguous, so the pose
estimate alone cannot certify arrival; look-alike textures elsewhere can match part of the view
perfectly, and the rest of the image then disagrees.
"""

from __future__ import annotations

import math

import networkx as nx
import numpy as np

from topomap.graph import TopoMap
from topomap.localize import Query
from topomap.matching import Verification
from topomap.retrieval import sad

__all__ = ["GoalAgreement", "UNRELATED_THUMBNAIL_SAD", "AWAY_HOPS"]

#: Patch-normalised thumbnails of unrelated images differ by ~2/sqrt(pi) = 1.13 (mean |N(0,2)|).
UNRELATED_THUMBNAIL_SAD = 2 / math.sqrt(math.pi)
#: Keyframes further than this many graph hops from the goal count as "away" from it.
AWAY_HOPS = 2


class GoalAgreement:
    """Image agreement with the keyframes of ``tmap`` (per-node figures cached).

    ``flow_bound``: largest median motion of the verified matches, a fraction of the image width;
    ``descriptor_fraction``: the whole-image descriptor must be closer to the keyframe's than this
    fraction of the keyframe's median distance to its neighbours' (``NavigateConfig.arrive_*``)."""

    def __init__(self, tmap: TopoMap, flow_bound: float, descriptor_fraction: float):
        self.map = tmap
        self.flow_bound = flow_bound
        self.descriptor_fraction = descriptor_fraction
        self._neighbour_sad: dict[int, float] = {}
        self._away: dict[int, np.ndarray | None] = {}

    def agrees(self, q: Query, v: Verification, node: int, flow_bound: float | None = None) -> bool:
        """The image of ``q`` (verified against the node's keyframe in ``v``) shows the node's view;
        ``flow_bound`` overrides the default bound on the matches' motion."""
        bound = self.flow_bound if flow_bound is None else flow_bound
        if not v.verified or v.flow_px >= bound * self.map.working_size[0]:
            return False
        goal_desc = self.map.nodes[node].descriptor
        if goal_desc is None or q.descriptor.size != goal_desc.size:
            return True  # no whole-image descriptor to compare
        d_goal = float(sad(q.descriptor, goal_desc[None])[0])
        if d_goal < self.descriptor_fraction * self.neighbour_distance(node):
            return True
        # where neighbouring keyframes look much alike, the bound above is tight: then it is enough
        # that no place away from the goal looks more like the current image
        others = self.away_descriptors(node)
        return others is None or d_goal < float(sad(q.descriptor, others).min())

    def away_descriptors(self, node: int) -> np.ndarray | None:
        """(M, D) thumbnail descriptors of the nodes more than :data:`AWAY_HOPS` hops from ``node``, or None."""
        if node not in self._away:
            near = set(nx.single_source_shortest_path_length(self.map.graph, node, cutoff=AWAY_HOPS))
            own = self.map.nodes[node].descriptor
            rows = [n.descriptor for i, n in self.map.nodes.items()
                    if i not in near and n.descriptor is not None and n.descriptor.size == own.size]
            self._away[node] = np.stack(rows) if rows else None
        return self._away[node]

    def neighbour_distance(self, node: int) -> float:
        """Median thumbnail distance between a node's keyframe and its neighbours'."""
        if node not in self._neighbour_sad:
            own = self.map.nodes[node].descriptor
            others = [self.map.nodes[n].descriptor for n in self.map.neighbours(node)]
            others = [d for d in others if d is not None and d.size == own.size]
            self._neighbour_sad[node] = float(np.median(sad(own, np.stack(others)))) if others else UNRELATED_THUMBNAIL_SAD
        return self._neighbour_sad[node]
