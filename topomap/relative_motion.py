"""Keyframe-pair geometry: what the two keyframe images of an edge tell about their relative pose,
computed once when the map is built or indexed and stored in ``edge.relative_motion``
(docs/theory.md section 4.4; the poses are section 3.2's, the walls section 3.4's).

The navigator needs, for two neighbouring keyframes, the heading of one relative to the other (at a
subgoal switch it predicts the heading to the next subgoal, which may lie a turn away), the wall
normals a planar view allows (the servo keeps the pose whose normal other views of the goal share)
and the distance between them in both scale conventions (their ratio makes the goal's distances
metric when the camera height is known). Matching A to B is not symmetric, so each direction of an
edge has its own record.

Stored form, JSON in ``edge.relative_motion`` (``null`` for a direction whose keyframes do not verify;
``null`` numbers for what their planar pose leaves undetermined)::

    {"version": 1, "a_in_b": PAIR | null, "b_in_a": PAIR | null}
    PAIR = {"theta_rad": number | null, "wall_normals_rad": [number, ...],
            "rho_depth_s": number | null, "rho_floor_s": number | null}

The relative-pose configuration they were computed with is ``map.meta["relative_motion"]``; a
navigator with another one, a map without the records (older, or edges added by hand) and malformed
records fall back to computing them from the keyframes (:class:`KeyframePairs`).
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass, replace

import numpy as np

from topomap.camera import CameraIntrinsics
from topomap.config import MatchConfig, RelativePoseConfig, to_dict
from topomap.features import Features
from topomap.graph import Edge, TopoMap
from topomap.matching import Verification, verify
from topomap.parallel import Executor
from topomap.servo.homography import wall_normals
from topomap.servo.pose import PoseStatus
from topomap.servo.relpose import relative_pose_with_scales

__all__ = ["PairMotion", "pair_motion", "annotate_edges", "KeyframePairs", "META_KEY", "SCALE_CLIP_FACTOR"]

log = logging.getLogger(__name__)

#: ``map.meta`` key of the relative-pose configuration the edges' records were computed with.
META_KEY = "relative_motion"
VERSION = 1
#: Below this scaled distance between the keyframes their scale ratio is noise.
MIN_RHO_S = 1e-3
#: A goal's metric scale stays within this factor of the nominal scale (either way).
SCALE_CLIP_FACTOR = 3.0


@dataclass(frozen=True)
class PairMotion:
    """Keyframe ``a`` seen from keyframe ``b`` (the servo's planar pose of ``a`` in ``b``'s frame).

    ``theta_rad``: heading of ``a`` relative to ``b`` [rad], NaN when the pose has none;
    ``wall_normals_rad``: the wall normals (in ``b``'s camera) the view allows where the translation
    resolves them; ``rho_depth_s, rho_floor_s``: the distance between them in the median-depth and
    the camera-height scale conventions (None unless both poses are OK and not nearly coincident).
    """

    theta_rad: float
    wall_normals_rad: tuple[float, ...] = ()
    rho_depth_s: float | None = None
    rho_floor_s: float | None = None

    def to_json(self) -> dict:
        return {"theta_rad": None if math.isnan(self.theta_rad) else self.theta_rad,
                "wall_normals_rad": list(self.wall_normals_rad),
                "rho_depth_s": self.rho_depth_s, "rho_floor_s": self.rho_floor_s}

    @classmethod
    def from_json(cls, d: dict) -> PairMotion:
        """Inverse of :meth:`to_json`; ValueError when ``d`` is not such a record."""
        if not isinstance(d, dict) or set(d) != {"theta_rad", "wall_normals_rad", "rho_depth_s", "rho_floor_s"}:
            raise ValueError("not a keyframe-pair record")
        theta, normals = _number(d["theta_rad"]), d["wall_normals_rad"]
        if not isinstance(normals, list) or len(normals) > 64 or any(_number(x) is None for x in normals):
            raise ValueError("bad wall normals")
        depth, floor = _number(d["rho_depth_s"]), _number(d["rho_floor_s"])
        if (depth is None) != (floor is None) or (depth is not None and not depth > 0):
            raise ValueError("bad scale pair")
        return cls(math.nan if theta is None else theta, tuple(float(x) for x in normals), depth, floor)


def _number(x) -> float | None:
    if x is None:
        return None
    if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
        raise ValueError("not a finite number")
    return float(x)


def pair_motion(fa: Features, fb: Features, camera: CameraIntrinsics, match: MatchConfig,
                geometry: RelativePoseConfig, verification: Verification | None = None) -> PairMotion | None:
    """Keyframe A (features ``fa``) seen from keyframe B; None when they do not verify.
    ``verification``: ``verify(fa, fb, match)`` when already known (the build verified its edges)."""
    v = verify(fa, fb, match) if verification is None else verification
    if not v.verified:
        return None
    cur, dst = fa.keypoints[v.inlier_matches.ia], fb.keypoints[v.inlier_matches.ib]
    # the distances are the essential matrix's (before a wall's homography picks a pose)
    pose, rho, rho_floor = relative_pose_with_scales(cur, dst, camera, geometry)
    theta = pose.theta if pose.status in (PoseStatus.OK, PoseStatus.PURE_ROTATION) else math.nan
    normals = wall_normals(pose, geometry.plane_min_t_over_d)
    if rho is not None and rho_floor is not None and rho > MIN_RHO_S:
        return PairMotion(theta, normals, rho, rho_floor)
    return PairMotion(theta, normals)


def _edge_task(args) -> dict:
    fa, fb, camera, match, geometry, v_ab, v_ba = args
    ab = pair_motion(fa, fb, camera, match, geometry, v_ab)
    ba = pair_motion(fb, fa, camera, match, geometry, v_ba)
    return {"version": VERSION, "a_in_b": ab.to_json() if ab else None, "b_in_a": ba.to_json() if ba else None}


def _stamp(geometry: RelativePoseConfig) -> dict:
    return json.loads(json.dumps(to_dict(geometry)))  # as the map file holds it (enums as names)


def annotate_edges(tmap: TopoMap, geometry: RelativePoseConfig | None = None, *,
                   executor: Executor | None = None, verified: dict[tuple[int, int], Verification] | None = None) -> int:
    """Compute ``relative_motion`` of every edge without one (of every edge when the map's were
    computed with another configuration), on ``executor`` if given. ``verified``: ``{(x, y):
    verify(features of x, features of y, map's match config)}`` already computed (by the build), reused
    for the direction "x seen from y". Returns how many were computed."""
    verified = verified or {}
    geometry = geometry or RelativePoseConfig()
    stamp = _stamp(geometry)
    same = isinstance(tmap.meta.get(META_KEY), dict) and tmap.meta[META_KEY].get("geometry") == stamp
    todo = [k for k, e in tmap.edges.items() if e.relative_motion is None or not same]

    def items() -> Iterator[tuple]:
        for a, b in todo:
            yield (tmap.nodes[a].features, tmap.nodes[b].features, tmap.camera, tmap.config.match, geometry,
                   verified.get((a, b)), verified.get((b, a)))

    results = executor.map(_edge_task, items()) if executor is not None else map(_edge_task, items())
    for key, motion in zip(todo, results):
        tmap.edges[key] = replace(tmap.edges[key], relative_motion=motion)
    tmap.meta[META_KEY] = {"version": VERSION, "geometry": stamp}
    return len(todo)


class KeyframePairs:
    """:class:`PairMotion` of neighbouring keyframes of ``tmap`` for a relative-pose configuration:
    read from the edges when they were computed with it, else computed (and cached either way)."""

    def __init__(self, tmap: TopoMap, geometry: RelativePoseConfig):
        self.map, self.geometry = tmap, geometry
        meta = tmap.meta.get(META_KEY)
        self.stored = isinstance(meta, dict) and meta.get("geometry") == _stamp(geometry)
        self._cache: dict[tuple[int, int], PairMotion | None] = {}
        self._views: dict[tuple[int, float | None, float], tuple[tuple[float, ...], float | None]] = {}

    def goal_view(self, node: int, camera_height_m: float | None, nominal_scale_m: float) -> tuple[tuple[float, ...], float | None]:
        """What the node keyframe's graph neighbours tell about its view: the normals of its wall,
        and its scale (metres per scaled unit) when the camera height is known, else None.

        Normals: each neighbour that sees the keyframe's view as one plane allows two, the wall's and
        a false one that depends on where the neighbour was taken; the servo keeps the pose whose
        normal agrees (:func:`~topomap.servo.homography.choose_plane_solution`). Scale: each
        neighbour's distance measured in both conventions, camera height (floor points) over median
        depth; the median of those, clipped to 1/SCALE_CLIP_FACTOR..SCALE_CLIP_FACTOR times
        ``nominal_scale_m``."""
        key = (node, camera_height_m, nominal_scale_m)
        if key not in self._views:
            normals: list[float] = []
            scales: list[float] = []
            for nb in self.map.neighbours(node):
                pair = self.motion(nb, node)
                if pair is None:
                    continue
                normals += pair.wall_normals_rad
                if camera_height_m is not None and pair.rho_depth_s is not None:
                    scales.append(camera_height_m * pair.rho_floor_s / pair.rho_depth_s)
            scale = None
            if scales:
                scale = float(np.clip(np.median(scales), nominal_scale_m / SCALE_CLIP_FACTOR, SCALE_CLIP_FACTOR * nominal_scale_m))
            self._views[key] = (tuple(normals), scale)
        return self._views[key]

    def floor_lengths_m(self, camera_height_m: float) -> dict[tuple[int, int], float]:
        """Each edge's length on the floor [m]: the median over its two directions of the keyframes'
        distance in the camera-height convention times ``camera_height_m``; edges whose keyframes give
        no such distance are left out. Read from the edges' records (computed where a map has none)."""
        out: dict[tuple[int, int], float] = {}
        for a, b in self.map.edges:
            rho = [p.rho_floor_s for p in (self.motion(a, b), self.motion(b, a)) if p is not None and p.rho_floor_s is not None]
            if rho:
                out[(a, b)] = camera_height_m * float(np.median(rho))
        return out

    def motion(self, a: int, b: int) -> PairMotion | None:
        """Keyframe ``a`` seen from keyframe ``b``; None when they do not verify."""
        if (a, b) not in self._cache:
            found, rec = self._read(self.map.edge(a, b), a) if self.stored else (False, None)
            if not found:
                m = self.map
                rec = pair_motion(m.nodes[a].features, m.nodes[b].features, m.camera, m.config.match, self.geometry)
            self._cache[(a, b)] = rec
        return self._cache[(a, b)]

    @staticmethod
    def _read(edge: Edge | None, a: int) -> tuple[bool, PairMotion | None]:
        rm = edge.relative_motion if edge is not None else None
        if not isinstance(rm, dict) or rm.get("version") != VERSION:
            return False, None
        side = rm.get("a_in_b" if a == edge.a else "b_in_a", False)
        if side is None:
            return True, None  # computed: they do not verify
        try:
            return True, PairMotion.from_json(side)
        except ValueError:
            log.warning("edge %d-%d holds a malformed relative motion; computing it from the keyframes", edge.a, edge.b)
            return False, None
