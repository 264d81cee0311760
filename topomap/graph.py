"""``TopoMap``: the appearance topological map in memory — nodes, edges, frames. No I/O here.

A *node* is a keyframe: its local features, a thumbnail, optionally its image and a whole-image
descriptor. A *frame* is any input image; each readable frame is represented by exactly one node
(the keyframe it was matched to while the map was built), which is what localization is scored
against. An *edge* joins two nodes whose images share geometrically verified matches, so that
servoing along it is possible:

* ``sequential`` — consecutive keyframes of one image sequence;
* ``loop`` — two non-consecutive nodes recognised as the same place (loop closure, or a link
  between sequences added with ``--append``);
* ``manual`` — added by a user.

*Aligned links* join keyframes of two experiences (build runs) that sequence alignment found to
show the same place where no geometry verifies it (night against day, an appearance-only map): not
edges — nothing can servo along them — but the same place for localization (:meth:`TopoMap.place_ids`,
the sequence filter's moves). Stored as ``arrays["aligned_links"]`` (M, 2) int64 and
``arrays["aligned_confidence"]`` (M,) float32, see :mod:`topomap.alignment`.
"""

from __future__ import annotations

import enum
from collections import Counter
from dataclasses import dataclass, field

import networkx as nx
import numpy as np

from topomap.camera import CameraIntrinsics
from topomap.config import BuildConfig
from topomap.errors import ConfigError, MapFormatError, NodeNotFoundError
from topomap.features import Features

__all__ = ["EdgeKind", "Node", "Edge", "FrameRecord", "TopoMap", "ALIGNED_LINKS", "ALIGNED_CONFIDENCE"]

#: ``TopoMap.arrays`` names of the aligned links: (M, 2) int64 node pairs and their (M,) confidence.
ALIGNED_LINKS = "aligned_links"
ALIGNED_CONFIDENCE = "aligned_confidence"


class EdgeKind(str, enum.Enum):
    SEQUENTIAL = "sequential"
    LOOP = "loop"
    MANUAL = "manual"


@dataclass
class Node:
    """A keyframe.

    ``id``: node id (0..); ``sequence``: which build run created it (0 = first build, 1 = first
    ``--append`` ...); ``frame_id``: the :class:`FrameRecord` whose image is the keyframe;
    ``source``: that image's file name; ``features``: its local features at the working resolution
    (a fresh build's are :class:`topomap.spill.SpilledFeatures`, read from disk when used);
    ``thumbnail``: (h, w) uint8; ``image``: (H, W) uint8 keyframe at the working resolution, or
    ``None`` when not stored; ``descriptor``: (D,) float32 whole-image descriptor or ``None``;
    ``image_data``: the keyframe image already encoded as the map stores it (JPEG/PNG bytes: a build
    keeps these rather than pixels, 5-10x less memory, on disk as :class:`topomap.spill.SpilledBytes`:
    read them with :func:`topomap.spill.as_bytes`) or ``None``;
    ``pose_gt``: ground-truth pose, used only for plots and scoring — never by localization or
    navigation.
    """

    id: int
    sequence: int
    frame_id: int
    source: str
    features: Features
    thumbnail: np.ndarray
    image: np.ndarray | None = None
    descriptor: np.ndarray | None = None
    pose_gt: tuple[float, ...] | None = None
    image_data: bytes | None = None  # or a topomap.spill.SpilledBytes


@dataclass(frozen=True)
class Edge:
    """An undirected edge ``a < b`` with its verification figures.

    ``inliers``: verified matches between the two keyframes; ``similarity``: inliers / features of
    the smaller keyframe, in [0, 1]; ``flow_px``: median image motion of the inliers [px] — large
    motion and few inliers make servoing along the edge hard; ``relative_motion``: the two
    keyframes' planar geometry, JSON-able (:mod:`topomap.relative_motion`), or None.
    """

    a: int
    b: int
    kind: EdgeKind
    inliers: int
    similarity: float
    flow_px: float = 0.0
    relative_motion: dict | None = field(default=None, hash=False)

    def __post_init__(self) -> None:
        if self.a == self.b:
            raise ValueError("an edge joins two different nodes")
        if self.a > self.b:
            a, b = self.b, self.a
            object.__setattr__(self, "a", a)
            object.__setattr__(self, "b", b)
        object.__setattr__(self, "kind", EdgeKind(self.kind))

    @property
    def key(self) -> tuple[int, int]:
        return (self.a, self.b)


@dataclass(frozen=True)
class FrameRecord:
    """One input image of a build. ``node`` is the node representing it, ``None`` if it was
    skipped (``status`` then says why: unreadable, too few features...).

    That node is the keyframe of its sequence nearest by frame index (ties: the earlier one, tracked
    against), since a new keyframe is the last frame that still matched the one before it; map files
    built before 2026-12-03 keep their stored assignment (the keyframe before)."""

    id: int
    sequence: int
    index: int  # position within its sequence
    source: str  # file name (or frame_000123 for videos)
    node: int | None
    status: str = "ok"


@dataclass
class TopoMap:
    """The map: nodes, edges and frames, with the camera and the config that built it."""

    camera: CameraIntrinsics
    config: BuildConfig = field(default_factory=BuildConfig)
    nodes: dict[int, Node] = field(default_factory=dict)
    edges: dict[tuple[int, int], Edge] = field(default_factory=dict)
    frames: list[FrameRecord] = field(default_factory=list)
    sequences: list[dict] = field(default_factory=list)  # per build run: source, frame count, time
    index: object | None = None  # retrieval.BowIndex (kept untyped to avoid an import cycle)
    meta: dict = field(default_factory=dict)  # JSON-able values; the map file keeps every key
    arrays: dict[str, np.ndarray] = field(default_factory=dict)  # named numeric arrays kept in the map file

    # ------------------------------------------------------------------ access
    @property
    def feature_kind(self) -> str:
        return self.config.features.kind

    @property
    def working_size(self) -> tuple[int, int]:
        """``(width, height)`` at which keypoints are expressed."""
        return (self.camera.width, self.camera.height)

    def node(self, node_id: int) -> Node:
        """The node with this id; an unknown id raises :class:`NodeNotFoundError` naming the valid range."""
        try:
            return self.nodes[int(node_id)]
        except (KeyError, ValueError, TypeError):
            raise NodeNotFoundError(
                f"node {node_id} is not in this map (it has {len(self.nodes)} nodes: {self._id_range()})"
            ) from None

    def _id_range(self) -> str:
        if not self.nodes:
            return "none"
        ids = sorted(self.nodes)
        return f"ids {ids[0]}..{ids[-1]}" if ids[-1] - ids[0] + 1 == len(ids) else f"ids {ids[:5]}..."

    def edge(self, a: int, b: int) -> Edge | None:
        return self.edges.get((min(a, b), max(a, b)))

    def neighbours(self, node_id: int) -> list[int]:
        self.node(node_id)
        return sorted({e.b if e.a == node_id else e.a for e in self.edges.values() if node_id in (e.a, e.b)})

    def linked(self, node_id: int) -> list[int]:
        """The node's graph neighbours and the nodes of other experiences aligned to it (the same
        place, :meth:`aligned_links`): everything localization counts as the node's neighbourhood."""
        twins = {b if a == node_id else a for a, b, _ in self.aligned_links() if node_id in (a, b)}
        return sorted(set(self.neighbours(node_id)) | twins)

    def node_of_frame(self, source: str) -> int | None:
        """The node representing the frame with this file name (``None`` if skipped or unknown)."""
        for f in self.frames:
            if f.source == source:
                return f.node
        return None

    # ------------------------------------------------------------------ mutation
    def add_node(self, node: Node) -> Node:
        if node.id in self.nodes:
            raise ValueError(f"node {node.id} exists")
        if node.features.kind != self.feature_kind:
            raise ConfigError(f"node {node.id} has {node.features.kind} features, the map {self.feature_kind}")
        self.nodes[node.id] = node
        return node

    def add_edge(self, edge: Edge) -> Edge:
        for n in (edge.a, edge.b):
            self.node(n)
        old = self.edges.get(edge.key)
        # a sequential edge keeps its kind if loop closure rediscovers it
        if old is None or (old.kind is not EdgeKind.SEQUENTIAL and edge.inliers > old.inliers):
            self.edges[edge.key] = edge
        return self.edges[edge.key]

    def next_node_id(self) -> int:
        return max(self.nodes) + 1 if self.nodes else 0

    # ------------------------------------------------------------------ graph views
    @property
    def graph(self) -> nx.Graph:
        """A networkx view: nodes carry ``source``, ``sequence``; edges ``kind``, ``inliers``,
        ``similarity``, ``flow_px``."""
        g = nx.Graph()
        for n in sorted(self.nodes.values(), key=lambda n: n.id):
            g.add_node(n.id, source=n.source, sequence=n.sequence, features=len(n.features))
        for e in sorted(self.edges.values(), key=lambda e: e.key):
            g.add_edge(e.a, e.b, kind=e.kind.value, inliers=e.inliers, similarity=e.similarity, flow_px=e.flow_px)
        return g

    def components(self) -> list[list[int]]:
        """Connected components, largest first, each a sorted list of node ids."""
        comps = [sorted(c) for c in nx.connected_components(self.graph)]
        return sorted(comps, key=lambda c: (-len(c), c[0]))

    def edges_by_kind(self) -> dict[str, int]:
        counts = Counter(e.kind.value for e in self.edges.values())
        return {k.value: counts.get(k.value, 0) for k in EdgeKind}

    def aligned_links(self) -> list[tuple[int, int, float]]:
        """``(a, b, confidence)`` per aligned link (see the module docstring), ``a`` < ``b``.

        The arrays may come from a stranger's file: a malformed pair of arrays, or a link naming a
        node that is not in the map or two nodes of one experience, raises :class:`MapFormatError`."""
        if ALIGNED_LINKS not in self.arrays and ALIGNED_CONFIDENCE not in self.arrays:
            return []
        pairs, conf = self.arrays.get(ALIGNED_LINKS), self.arrays.get(ALIGNED_CONFIDENCE)
        fix = "the file is damaged: rebuild the map"
        if (pairs is None or conf is None or pairs.ndim != 2 or pairs.shape[1:] != (2,) or pairs.dtype.kind not in "iu"
                or conf.shape != (len(pairs),) or conf.dtype.kind != "f" or not np.all((conf >= 0) & (conf <= 1))):
            raise MapFormatError(f"the map's aligned links are malformed; {fix}")
        out = []
        for (a, b), c in zip(pairs.tolist(), conf.tolist()):  # O(links): no pass over the nodes
            na, nb = self.nodes.get(a), self.nodes.get(b)
            if na is None or nb is None or na.sequence == nb.sequence:
                raise MapFormatError(f"the map's aligned link {a}-{b} does not join nodes of two experiences; {fix}")
            out.append((min(a, b), max(a, b), c))
        return out

    def set_aligned_links(self, links: list[tuple[int, int, float]]) -> None:
        """Replace the aligned links (``[(a, b, confidence)]``; none: the arrays are removed)."""
        for a, b, _ in links:
            self.node(a), self.node(b)
        if not links:
            self.arrays.pop(ALIGNED_LINKS, None)
            self.arrays.pop(ALIGNED_CONFIDENCE, None)
            return
        links = sorted((min(a, b), max(a, b), c) for a, b, c in links)
        self.arrays[ALIGNED_LINKS] = np.array([(a, b) for a, b, _ in links], np.int64).reshape(-1, 2)
        self.arrays[ALIGNED_CONFIDENCE] = np.array([c for *_, c in links], np.float32)

    def experiences(self) -> list[dict]:
        """One entry per build run (an *experience* of the place: another day, season, lighting):
        ``sequence``, ``source``, ``nodes``, ``links`` = {other sequence: loop edges joining them}
        and ``aligned`` = {other sequence: aligned links joining them}."""
        count = Counter(n.sequence for n in self.nodes.values())
        links: dict[int, Counter] = {s: Counter() for s in count}
        aligned: dict[int, Counter] = {s: Counter() for s in count}
        for e in self.edges.values():
            sa, sb = self.nodes[e.a].sequence, self.nodes[e.b].sequence
            if sa != sb:
                links[sa][sb] += 1
                links[sb][sa] += 1
        for a, b, _ in self.aligned_links():
            sa, sb = self.nodes[a].sequence, self.nodes[b].sequence
            aligned[sa][sb] += 1
            aligned[sb][sa] += 1
        return [{"sequence": s, "source": (self.sequences[s].get("source") if s < len(self.sequences) else None),
                 "nodes": count[s], "links": dict(sorted(links[s].items())),
                 "aligned": dict(sorted(aligned[s].items()))} for s in sorted(count)]

    def place_ids(self) -> dict[int, int]:
        """Node -> shared place: the smallest node id among the node and the nodes of other experiences
        it is joined to by an edge or an aligned link, so that a place mapped in several experiences
        answers as one."""
        place = {n: n for n in self.nodes}
        joins = [(e.a, e.b) for e in self.edges.values() if self.nodes[e.a].sequence != self.nodes[e.b].sequence]
        joins += [(a, b) for a, b, _ in self.aligned_links()]
        for a, b in joins:
            low = min(place[a], place[b], a, b)
            place[a] = min(place[a], low)
            place[b] = min(place[b], low)
        return place

    def summary(self) -> dict:
        """Counts for ``topomap info``: JSON-able."""
        nfeat = [len(n.features) for n in self.nodes.values()]
        return {
            "nodes": len(self.nodes),
            "frames": len(self.frames),
            "frames_skipped": sum(1 for f in self.frames if f.node is None),
            "edges": len(self.edges),
            "edges_by_kind": self.edges_by_kind(),
            "components": len(self.components()) if self.nodes else 0,
            "features": {
                "kind": self.feature_kind,
                "total": int(sum(nfeat)),
                "per_node_mean": float(np.mean(nfeat)) if nfeat else 0.0,
            },
            "sequences": len(self.sequences),
            "experiences": self.experiences(),
            "working_size": list(self.working_size),
            "camera": {"fx": self.camera.fx, "fy": self.camera.fy, "cx": self.camera.cx, "cy": self.camera.cy, "source": self.camera.source},
            "index": self.index is not None,
        }
