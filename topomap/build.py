"""Image sequence -> keyframes -> sequential and loop-closure edges (THESIS.md section 4).

Keyframing: each frame is matched to the current keyframe with epipolar verification. While they
share enough verified matches, which moved little across the image, the frame is *represented* by the
keyframe's node. When the matches fall below the threshold (or moved too far), the last frame that
still matched well becomes the next keyframe (so
consecutive keyframes keep plenty of common, verified features — servoing between them stays
feasible, far above the 3-point minimum of THESIS.md section 3) and the frame is matched again
against it; if even that fails, the frame itself starts a node.

Loop closure: once all frames are in, a bag-of-words index over the keyframes proposes, for each new
node, the ``loop_shortlist_k`` most similar nodes (not all pairs); each candidate is verified
geometrically and becomes a ``loop`` edge if it keeps enough epipolar inliers.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from topomap.camera import CameraIntrinsics
from topomap.config import BuildConfig
from topomap.errors import ConfigError, DatasetError
from topomap.features import Features, detector, extract
from topomap.graph import Edge, EdgeKind, FrameRecord, Node, TopoMap
from topomap.images import ImageSequence, open_sequence, to_working_resolution, working_size
from topomap.matching import Verification, verify
from topomap.retrieval import BowIndex, Vocabulary, thumbnail_descriptor, vocabulary_size

__all__ = ["BuildProgress", "build_map", "build_index", "descriptor_size", "make_thumbnail", "teach_world_record",
           "TEACH_WORLD_KEY"]

log = logging.getLogger(__name__)

#: Width of the whole-image (patch-normalised thumbnail) descriptor [px]; height follows the aspect.
DESCRIPTOR_WIDTH = 32
DESCRIPTOR_PATCH = 8
#: Frames with a side shorter than this are skipped: neither keypoints nor the whole-image
#: descriptor (DESCRIPTOR_WIDTH px wide) carry information below it [px].
MIN_IMAGE_PX = 32


@dataclass(frozen=True)
class BuildProgress:
    """Reported to ``on_progress`` during a build. ``stage``: ``frames`` | ``loops`` | ``index``."""

    stage: str
    done: int
    total: int
    nodes: int
    edges: int


def descriptor_size(width: int, height: int) -> tuple[int, int]:
    """``(w, h)`` of the whole-image descriptor for images of this aspect (multiples of the patch)."""
    h = max(DESCRIPTOR_PATCH, int(round(DESCRIPTOR_WIDTH * height / width / DESCRIPTOR_PATCH)) * DESCRIPTOR_PATCH)
    return DESCRIPTOR_WIDTH, h


def make_thumbnail(image: np.ndarray, longest_px: int) -> np.ndarray:
    h, w = image.shape
    s = longest_px / max(h, w)
    if s >= 1:
        return image.copy()
    return cv2.resize(image, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA)


@dataclass
class _Candidate:
    """A frame that may become a keyframe: its record index, working image and features."""

    record: int
    image: np.ndarray
    features: Features
    link: Verification | None = None  # verification against the keyframe it was matched to


def _is_kept(v: Verification, keyframe: Features, cfg: BuildConfig) -> bool:
    """The frame stays with the keyframe: enough verified matches, moved little across the image."""
    need = max(cfg.keyframe_min_inliers, int(np.ceil(cfg.keyframe_min_ratio * len(keyframe))))
    return v.inliers >= need and v.flow_px <= cfg.keyframe_max_flow * keyframe.image_size[0]


def build_map(
    source: str | Path | ImageSequence,
    config: BuildConfig | None = None,
    camera: CameraIntrinsics | None = None,
    *,
    base: TopoMap | None = None,
    every: int = 1,
    on_progress: Callable[[BuildProgress], None] | None = None,
) -> TopoMap:
    """Build a map from an image sequence, or extend ``base`` with a new sequence (``--append``).

    ``source``: image folder, video, list file or an :class:`ImageSequence`; ``config``: defaults
    to :class:`BuildConfig` (for ``base`` the map's own config is used); ``camera``: intrinsics of
    the *input* images (default: :meth:`CameraIntrinsics.default`). Unreadable frames are skipped,
    logged and recorded. Returns the map; ``map.sequences[-1]`` summarises this run.
    """
    t0 = time.perf_counter()
    seq = source if isinstance(source, ImageSequence) else open_sequence(source, every)
    if base is not None:
        if config is not None and config.features.kind != base.config.features.kind:
            raise ConfigError(
                f"the map uses {base.config.features.kind} features; cannot append a sequence with {config.features.kind}"
            )
        config = base.config
        if camera is not None:
            log.warning("--camera ignored when appending: the map's own intrinsics are used")
    config = config or BuildConfig()
    detector(config.features.kind)  # fail early on an unknown feature type
    tmap = base if base is not None else TopoMap(camera=CameraIntrinsics(1.0, 1.0, 0.0, 0.0), config=config)
    sequence_id = len(tmap.sequences)
    first_node = tmap.next_node_id()
    first_frame = len(tmap.frames)
    work_size = tmap.working_size if base is not None else None
    input_size: tuple[int, int] | None = None
    skipped: list[tuple[str, str]] = []
    total = len(seq)

    keyframe: _Candidate | None = None  # current keyframe (its node id is frames[...].node)
    keyframe_node = -1
    last_good: _Candidate | None = None

    def new_node(c: _Candidate, prev_node: int | None, link: Verification | None) -> int:
        nid = tmap.next_node_id()
        rec = tmap.frames[c.record]
        tmap.add_node(
            Node(
                id=nid, sequence=sequence_id, frame_id=rec.id, source=rec.source, features=c.features,
                thumbnail=make_thumbnail(c.image, config.thumbnail_px),
                image=c.image if config.store_images else None,
                descriptor=thumbnail_descriptor(c.image, descriptor_size(*work_size), DESCRIPTOR_PATCH),
            )
        )
        tmap.frames[c.record] = replace(rec, node=nid)
        if prev_node is not None and prev_node >= 0:
            v = link
            tmap.add_edge(Edge(prev_node, nid, EdgeKind.SEQUENTIAL, v.inliers if v else 0,
                               v.similarity if v else 0.0, v.flow_px if v else 0.0))
        return nid

    for frame in seq:
        fid = len(tmap.frames)
        if frame.image is None:
            skipped.append((frame.name, frame.error or "unreadable"))
            log.warning("skipped %s: %s", frame.name, frame.error)
            tmap.frames.append(FrameRecord(fid, sequence_id, frame.index, frame.name, None, "unreadable"))
            _report(on_progress, "frames", frame.index + 1, total, tmap)
            continue
        h, w = frame.image.shape
        if min(w, h) < MIN_IMAGE_PX:
            reason = f"{w}x{h} px is too small; images need at least {MIN_IMAGE_PX} px on each side"
            skipped.append((frame.name, reason))
            log.warning("skipped %s: %s", frame.name, reason)
            tmap.frames.append(FrameRecord(fid, sequence_id, frame.index, frame.name, None, "too small"))
            _report(on_progress, "frames", frame.index + 1, total, tmap)
            continue
        if work_size is None:
            work_size = working_size(w, h, config.features.resize_max_px, config.features.upscale_min_px,
                                     config.features.max_upscale)
            cam_in = camera.fitted_to(w, h) if camera is not None else CameraIntrinsics.default(w, h)
            tmap.camera = cam_in.fitted_to(*work_size)
        if input_size is None:
            input_size = (w, h)
        elif (w, h) != input_size:
            log.warning("%s is %dx%d, the sequence %dx%d: resized to the map's working size", frame.name, w, h, *input_size)
        image = to_working_resolution(frame.image, work_size)
        feats = extract(image, config.features)
        tmap.frames.append(FrameRecord(fid, sequence_id, frame.index, frame.name, None, "ok"))
        cand = _Candidate(fid, image, feats)

        if keyframe is None:
            keyframe, keyframe_node, last_good = cand, new_node(cand, None, None), None
        else:
            v = verify(keyframe.features, feats, config.match)
            if _is_kept(v, keyframe.features, config):
                tmap.frames[fid] = replace(tmap.frames[fid], node=keyframe_node)
                cand.link, last_good = v, cand
            else:
                if last_good is not None:
                    # the last frame that still matched well becomes the next keyframe
                    prev = keyframe_node
                    keyframe, keyframe_node = last_good, new_node(last_good, prev, last_good.link)
                    last_good = None
                    v = verify(keyframe.features, feats, config.match)
                if _is_kept(v, keyframe.features, config):
                    tmap.frames[fid] = replace(tmap.frames[fid], node=keyframe_node)
                    cand.link, last_good = v, cand
                else:
                    prev = keyframe_node
                    keyframe, keyframe_node, last_good = cand, new_node(cand, prev, v), None
        _report(on_progress, "frames", frame.index + 1, total, tmap)

    read = sum(1 for f in tmap.frames[first_frame:] if f.status == "ok")
    if read == 0:
        reasons = "; ".join(f"{n}: {r}" for n, r in skipped[:3]) or "it holds no frames"
        raise DatasetError(f"no usable image in {seq.source} ({reasons})")

    tmap.meta["descriptor"] = {"kind": "thumbnail", "size": list(descriptor_size(*work_size)), "patch": DESCRIPTOR_PATCH}
    if (taught := teach_world_record(seq.source)) is not None:
        if TEACH_WORLD_KEY not in tmap.meta:
            tmap.meta[TEACH_WORLD_KEY] = taught
        elif tmap.meta[TEACH_WORLD_KEY].get("world") != taught["world"]:
            log.warning("%s was taught in another world than the map's first run; the map keeps the first", seq.source)
    new_ids = [n for n in sorted(tmap.nodes) if n >= first_node]
    build_index(tmap, on_progress)
    loops = _close_loops(tmap, new_ids, config, on_progress)
    tmap.sequences.append(
        {
            "source": str(seq.source),
            "kind": seq.kind,
            "frames": len(tmap.frames) - first_frame,
            "frames_read": read,
            "frames_skipped": len(skipped),
            "skipped": [{"frame": n, "reason": r} for n, r in skipped],
            "nodes_added": len(new_ids),
            "loop_edges_added": loops,
            "seconds": round(time.perf_counter() - t0, 3),
            "input_size": list(input_size) if input_size else None,
        }
    )
    return tmap


#: Meta key of the world a simulator teach run was recorded in (see :func:`teach_world_record`).
TEACH_WORLD_KEY = "teach_world"
_TEACH_FILE_MAX_BYTES = 20_000_000  # a world file is tens of kB; refuse to read anything huge


def teach_world_record(source) -> dict | None:
    """What a simulator teach folder says about its world, for the map's ``teach_world`` meta key:
    ``{"world": <world.json>, "source": folder, "route", "vehicle", "conditions"}`` (the last three
    from ``teach.json``, None when absent). None when ``source`` is not such a folder; a damaged
    world.json is logged and skipped: the map builds from the images alone."""
    import json

    folder = Path(str(source))
    path = folder / "world.json"
    if not folder.is_dir() or not path.is_file():
        return None
    try:
        if path.stat().st_size > _TEACH_FILE_MAX_BYTES:
            raise ValueError(f"larger than {_TEACH_FILE_MAX_BYTES // 1_000_000} MB")
        world = json.loads(path.read_text())
        if not isinstance(world, dict) or world.get("format") != "topomap-world":
            raise ValueError("not a topomap world file")
        run = folder / "teach.json"
        teach = json.loads(run.read_text()) if run.is_file() and run.stat().st_size < _TEACH_FILE_MAX_BYTES else {}
        if not isinstance(teach, dict):
            teach = {}
    except (OSError, UnicodeDecodeError, ValueError) as e:  # JSONDecodeError is a ValueError
        log.warning("not recording the teach world of %s: %s is unreadable (%s)", folder, path.name, e)
        return None
    return {"world": world, "source": str(folder.resolve()), "route": teach.get("route"),
            "vehicle": teach.get("vehicle"), "conditions": teach.get("conditions")}


def _report(cb, stage: str, done: int, total: int, m: TopoMap) -> None:
    if cb is not None:
        cb(BuildProgress(stage, done, total, len(m.nodes), len(m.edges)))


def build_index(tmap: TopoMap, on_progress: Callable[[BuildProgress], None] | None = None) -> BowIndex | None:
    """(Re)build the map's place-recognition index from its nodes' features (``topomap index``).

    The vocabulary is trained on the map's own keyframe descriptors (seeded k-means). A map whose
    keyframes hold almost no features gets no index (``None``).
    """
    _report(on_progress, "index", 0, 1, tmap)
    feats = {n.id: n.features for n in tmap.nodes.values()}
    desc = [f.descriptors for f in feats.values() if len(f)]
    if sum(len(d) for d in desc) < 64:
        tmap.index = None
        return None
    cfg = tmap.config
    desc = np.concatenate(desc)
    voc = Vocabulary.train(desc, cfg.features.kind, vocabulary_size(len(desc), cfg.vocabulary_words), cfg.seed)
    tmap.index = BowIndex.build(voc, feats)
    _report(on_progress, "index", 1, 1, tmap)
    return tmap.index


def _close_loops(tmap: TopoMap, new_ids: list[int], cfg: BuildConfig, on_progress) -> int:
    """Verify the appearance shortlist of every new node; add ``loop`` edges. Returns how many."""
    index: BowIndex | None = tmap.index
    if index is None or len(tmap.nodes) < 3:
        return 0
    tested: set[tuple[int, int]] = set()
    added = 0
    all_ids = set(tmap.nodes)
    by_sequence: dict[int, set[int]] = {}
    for n in tmap.nodes.values():
        by_sequence.setdefault(n.sequence, set()).add(n.id)
    seq_adj: dict[int, list[int]] = {}
    for e in tmap.edges.values():
        if e.kind is EdgeKind.SEQUENTIAL:
            seq_adj.setdefault(e.a, []).append(e.b)
            seq_adj.setdefault(e.b, []).append(e.a)
    for i, nid in enumerate(new_ids):
        node = tmap.nodes[nid]
        if len(node.features) < cfg.match.min_inliers:
            continue
        near = _within_steps(seq_adj, nid, cfg.loop_min_separation)
        scores = index.scores(node.features)
        own = by_sequence[node.sequence]
        candidates = index.top_k(scores, cfg.loop_shortlist_k, near | (all_ids - own))
        if len(own) < len(all_ids):
            candidates += index.top_k(scores, cfg.loop_shortlist_k, own)
        for cid, score in candidates:
            pair = (min(nid, cid), max(nid, cid))
            if score <= 0 or pair in tested or pair in tmap.edges:
                continue
            tested.add(pair)
            other = tmap.nodes[cid]
            v = verify(node.features, other.features, cfg.match)
            if v.inliers >= cfg.loop_min_inliers and v.inlier_ratio >= cfg.loop_min_inlier_ratio:
                tmap.add_edge(Edge(nid, cid, EdgeKind.LOOP, v.inliers, v.similarity, v.flow_px))
                added += 1
        _report(on_progress, "loops", i + 1, len(new_ids), tmap)
    return added


def _within_steps(adj: dict[int, list[int]], nid: int, steps: int) -> set[int]:
    """Nodes reachable from ``nid`` in fewer than ``steps`` edges of ``adj`` (``nid`` included)."""
    seen, frontier = {nid}, [nid]
    for _ in range(max(0, steps - 1)):
        frontier = [m for n in frontier for m in adj.get(n, []) if m not in seen]
        seen.update(frontier)
    return seen
