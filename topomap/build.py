"""Image sequence -> keyframes -> sequential and loop-closure edges (docs/theory.md section 4).

The build reads as hloc's pipelines do, one stage after the other, each a plain function:
sources (:func:`_frame_tasks`) -> features (:func:`prepare_frame`, per frame) -> keyframes
(:func:`_select_keyframes`) -> index (:func:`build_index`) -> loops (:func:`_close_loops`) ->
alignment of an appended experience (:func:`topomap.alignment.align_experience`) -> calibration; the
store (``topomap.store``) writes the result. The per-frame and per-pair work is pure and goes to an
:class:`~topomap.parallel.Executor` (in-process, a process pool or Dask), which hands results back
in order: the map is the same at any worker count.

Keyframing: each frame is matched to the current keyframe with epipolar verification. While they
share enough verified matches, which moved little across the image, the frame is *represented* by the
keyframe's node. When the matches fall below the threshold (or moved too far), the last frame that
still matched well becomes the next keyframe (so
consecutive keyframes keep plenty of common, verified features — servoing between them stays
feasible, far above the 3-point minimum of docs/theory.md section 3) and the frame is matched again
against it; if even that fails, the frame itself starts a node. A frame with fewer keypoints than
a verification needs (``match.min_inliers``: a turn facing blank paint) in a sequence whose keyframes
so far hold a median of at least ``localize.MIN_FEATURES_FOR_BOW`` never becomes a keyframe: no
image could certify it as a goal, so it is represented by the last keyframe that had features (the
same spot, when the teach run turned in place). The decisions are sequential, but
with several workers the verifications of the next frames against the current keyframe are run
ahead, in parallel (speculatively: those past a keyframe change are dropped), which gives the
same keyframes as one frame at a time.

Memory stays bounded whatever the length of the sequence: frames stream through a window of a few
per worker; only keyframes are kept (thumbnail and descriptor in memory; features and encoded image
on disk until the map is saved, :mod:`topomap.spill`).

Loop closure: once all frames are in, a bag-of-words index over the keyframes proposes, for each new
node, the ``loop_shortlist_k`` most similar nodes (not all pairs); each candidate is verified
geometrically (in parallel) and becomes a ``loop`` edge if it keeps enough epipolar inliers.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from topomap.camera import CameraIntrinsics
from topomap.config import BuildConfig, FeatureConfig, MatchConfig
from topomap.errors import CalibrationError, ClusterError, ConfigError, DatasetError
from topomap.features import Features, detector, extract
from topomap.graph import Edge, EdgeKind, FrameRecord, Node, TopoMap
from topomap.images import ImageSequence, open_sequence, read_image, to_working_resolution, working_size
from topomap.matching import Verification, verify
from topomap.parallel import Executor, InlineExecutor
from topomap.calibration import CALIBRATION_KEY, Calibration
from topomap.relative_motion import annotate_edges
from topomap.spill import Spill
from topomap.retrieval import (
    THUMBNAIL_PATCH,
    THUMBNAIL_SIZE,
    BowIndex,
    GlobalDescriptors,
    Vocabulary,
    make_thumbnail,
    thumbnail_descriptor,
    vocabulary_size,
)
from topomap.self_supervision import calibrate_map
from topomap.localize import MIN_FEATURES_FOR_BOW

__all__ = ["BuildProgress", "FrameTask", "PreparedFrame", "build_map", "build_index", "prepare_frame",
           "calibrate", "descriptor_size", "index_global_descriptors", "make_thumbnail", "teach_world_record", "TEACH_WORLD_KEY"]

log = logging.getLogger(__name__)

#: Width of the whole-image (patch-normalised thumbnail) descriptor [px]; height follows the aspect.
DESCRIPTOR_WIDTH = THUMBNAIL_SIZE[0]
DESCRIPTOR_PATCH = THUMBNAIL_PATCH
#: Frames with a side shorter than this are skipped: neither keypoints nor the whole-image
#: descriptor (DESCRIPTOR_WIDTH px wide) carry information below it [px].
MIN_IMAGE_PX = 32
#: A map whose keyframes hold fewer descriptors than this in all gets no vocabulary index.
MIN_INDEX_DESCRIPTORS = 64


@dataclass(frozen=True)
class BuildProgress:
    """Reported to ``on_progress`` during a build. ``stage``: ``frames`` | ``index`` | ``loops`` |
    ``align`` (``--append``) | ``motion`` (the keyframe pairs' geometry) | ``calibrate``."""

    stage: str
    done: int
    total: int
    nodes: int
    edges: int


def descriptor_size(width: int, height: int) -> tuple[int, int]:
    """``(w, h)`` of the whole-image descriptor for images of this aspect (multiples of the patch)."""
    h = max(DESCRIPTOR_PATCH, int(round(DESCRIPTOR_WIDTH * height / width / DESCRIPTOR_PATCH)) * DESCRIPTOR_PATCH)
    return DESCRIPTOR_WIDTH, h




# ============================================================================= stage: sources
@dataclass(frozen=True)
class FrameTask:
    """One frame to prepare: read from ``path`` where the worker runs, or given as ``image``
    ((H, W) uint8, decoded here: video frames); ``work_size``: ``(w, h)`` of the map."""

    index: int
    name: str
    path: str | None
    image: np.ndarray | None
    work_size: tuple[int, int]
    features: FeatureConfig
    error: str | None = None


@dataclass(frozen=True)
class PreparedFrame:
    """A frame after decoding and extraction. ``status``: ``ok`` | ``unreadable`` | ``too small``;
    ``reason``: why it was skipped; ``missing``: the worker could not open the file at all (not a
    damaged image); ``input_size``: ``(w, h)`` as read; ``image``: (h, w) uint8 at the working
    resolution; ``features`` at that resolution (``None`` unless ``ok``)."""

    index: int
    name: str
    status: str
    reason: str | None = None
    missing: bool = False
    input_size: tuple[int, int] | None = None
    image: np.ndarray | None = None
    features: Features | None = None


def _decode(task: FrameTask) -> tuple[np.ndarray | None, str | None, bool]:
    """(image, error, missing) of a task: its given image or the file read here."""
    if task.image is not None or task.path is None:
        return task.image, task.error, False
    try:
        return read_image(task.path), None, False
    except DatasetError as e:
        return None, str(e), not Path(task.path).is_file()


def prepare_frame(task: FrameTask) -> PreparedFrame:
    """The features stage, for one frame (pure, runs on any worker): decode, check the size, bring to
    the working resolution, extract local features."""
    image, error, missing = _decode(task)
    if image is None:
        return PreparedFrame(task.index, task.name, "unreadable", error or "unreadable", missing)
    h, w = image.shape
    if min(w, h) < MIN_IMAGE_PX:
        reason = f"{w}x{h} px is too small; images need at least {MIN_IMAGE_PX} px on each side"
        return PreparedFrame(task.index, task.name, "too small", reason, input_size=(w, h))
    work = to_working_resolution(image, task.work_size)
    return PreparedFrame(task.index, task.name, "ok", input_size=(w, h), image=work, features=extract(work, task.features))


def _first_readable(frames: Iterator, config: BuildConfig):
    """Frames before the first readable one (they fix nothing) and that one, read here: its size
    fixes the map's working size before any work is handed out."""
    before = []
    for frame in frames:
        if frame.image is not None and min(frame.image.shape) >= MIN_IMAGE_PX:
            return before, frame
        before.append(frame)
    return before, None


def _frame_tasks(seq: ImageSequence, work_size: tuple[int, int], config: BuildConfig, start: int) -> Iterator[FrameTask]:
    """The sequence's frames from ``start`` on as tasks: file paths (read by the workers) for
    folders and lists, decoded images for videos."""
    paths = seq.paths
    if paths is not None:
        for i in range(start, len(paths)):
            yield FrameTask(i, paths[i].name, str(paths[i]), None, work_size, config.features)
        return
    for frame in seq:
        if frame.index >= start:
            yield FrameTask(frame.index, frame.name, None, frame.image, work_size, config.features, frame.error)


# ============================================================================= stage: keyframes
def _verify_pair(a: Features, b: Features, config: MatchConfig) -> Verification:
    """Geometric verification of one pair (pure; a task of the keyframe and loop stages). The edges'
    verifications are kept until the motion stage, which reuses them (:func:`annotate_edges`)."""
    return verify(a, b, config)


def _verify_task(args: tuple[Features, Features, MatchConfig]) -> Verification:
    return _verify_pair(*args)


def _for_motion(v: Verification) -> Verification:
    """What the motion stage reads of an edge's verification (:func:`~topomap.relative_motion.pair_motion`:
    whether it verified and its inlier matches), without the outliers the build no longer needs;
    its ``inlier_ratio`` is then 1."""
    inliers = v.inlier_matches  # copies: the full match arrays are freed with ``v``
    return replace(v, matches=inliers, inlier_mask=np.ones(len(inliers), bool))


def _is_kept(v: Verification, keyframe: Features, cfg: BuildConfig) -> bool:
    """The frame stays with the keyframe: enough verified matches, moved little across the image."""
    need = max(cfg.keyframe_min_inliers, int(np.ceil(cfg.keyframe_min_ratio * len(keyframe))))
    return v.inliers >= need and v.flow_px <= cfg.keyframe_max_flow * keyframe.image_size[0]


@dataclass
class _Candidate:
    """A frame that may become a keyframe: its record index, working image and features."""

    record: int
    image: np.ndarray
    features: Features
    link: Verification | None = None  # verification against the keyframe it was matched to


class _Speculation:
    """Verifications of upcoming frames against the current keyframe, run ahead on the executor.

    ``depth`` of them are in flight at most (0: none, every verification is done when asked).
    A keyframe change drops them (their answers were against the old keyframe): the keyframes are
    exactly those of the one-at-a-time algorithm; only some work is wasted. To waste little, the
    look-ahead follows how many frames a keyframe has kept lately.
    """

    def __init__(self, executor: Executor, match: MatchConfig, depth: int):
        self.executor, self.match, self.max_depth = executor, match, max(0, depth)
        self.keyframe: Features | None = None
        self.futures: dict[int, object] = {}
        self.run_length = float(self.max_depth)  # frames kept per keyframe, smoothed

    def reset(self, keyframe: Features) -> None:
        if self.keyframe is not None and self.keyframe is not keyframe:
            for fut in self.futures.values():  # not started yet: never run
                getattr(fut, "cancel", lambda: None)()
            self.futures.clear()
        self.keyframe = keyframe

    def ahead(self, frames: Iterable[PreparedFrame]) -> None:
        depth = min(self.max_depth, max(1, int(round(self.run_length))))
        for f in frames:
            if len(self.futures) >= depth:
                break
            if f.status == "ok" and f.index not in self.futures:
                self.futures[f.index] = self.executor.submit(_verify_pair, self.keyframe, f.features, self.match)

    def result(self, f: PreparedFrame) -> Verification:
        fut = self.futures.pop(f.index, None)
        return fut.result() if fut is not None else _verify_pair(self.keyframe, f.features, self.match)

    def kept_run(self, frames_kept: int) -> None:
        self.run_length = 0.7 * self.run_length + 0.3 * frames_kept


def _move_past_midpoint(tmap: TopoMap, prev_record: int, prev_node: int, next_record: int, next_node: int) -> None:
    """The frames of ``prev_node`` between two keyframes that are nearer (by frame index) to the new
    one are represented by it: it is the last frame that still matched the previous keyframe, so the
    frames just before it are nearer to it. Ties stay with the previous keyframe (tracked against)."""
    a, b = tmap.frames[prev_record].index, tmap.frames[next_record].index
    for fid in range(prev_record + 1, next_record):
        f = tmap.frames[fid]
        if f.node == prev_node and f.index - a > b - f.index:
            tmap.frames[fid] = replace(f, node=next_node)


def _select_keyframes(frames: Iterator[PreparedFrame], tmap: TopoMap, config: BuildConfig, sequence_id: int,
                      executor: Executor, new_node: Callable, on_frame: Callable[[PreparedFrame], None]) -> None:
    """The keyframes stage: assign every prepared frame (in order) to a node, creating nodes and
    sequential edges through ``new_node(candidate, previous node, link)``; a frame is first given the
    keyframe it is tracked against and moves to the next one if that is nearer (:func:`_move_past_midpoint`)."""
    keyframe: _Candidate | None = None
    keyframe_node = -1
    last_good: _Candidate | None = None
    kept = 0
    spec = _Speculation(executor, config.match, executor.workers if executor.workers > 1 else 0)
    lookahead = max(1, spec.max_depth)
    buffer: deque[PreparedFrame] = deque()
    source = iter(frames)
    exhausted = False

    keyframe_features: list[int] = []  # this sequence's keyframes so far: is it a map of keypoints?

    def start_keyframe(c: _Candidate, node: int) -> None:
        nonlocal keyframe, keyframe_node, kept
        if keyframe is not None:
            spec.kept_run(kept)
            _move_past_midpoint(tmap, keyframe.record, keyframe_node, c.record, node)
        keyframe, keyframe_node, kept = c, node, 0
        keyframe_features.append(len(c.features))
        spec.reset(c.features)

    while True:
        while not exhausted and len(buffer) < lookahead + 1:
            try:
                buffer.append(next(source))
            except StopIteration:
                exhausted = True
        if not buffer:
            break
        frame = buffer.popleft()
        fid = len(tmap.frames)
        if frame.status != "ok":
            tmap.frames.append(FrameRecord(fid, sequence_id, frame.index, frame.name, None, frame.status))
            on_frame(frame)
            continue
        tmap.frames.append(FrameRecord(fid, sequence_id, frame.index, frame.name, None, "ok"))
        cand = _Candidate(fid, frame.image, frame.features)
        if keyframe is None:
            start_keyframe(cand, new_node(cand, None, None))
            last_good = None
        elif len(frame.features) < config.match.min_inliers and np.median(keyframe_features) >= MIN_FEATURES_FOR_BOW:
            # too few keypoints to ever verify (a turn facing blank paint) in a map of keypoints: the
            # frame joins the last view that had features instead of becoming a keyframe no image could
            # certify (an appearance-only map, e.g. Nordland's ~23 a frame, keeps every frame)
            if last_good is not None:
                start_keyframe(last_good, new_node(last_good, keyframe_node, last_good.link))
                last_good = None
            tmap.frames[fid] = replace(tmap.frames[fid], node=keyframe_node)
        else:
            spec.ahead(buffer)
            v = spec.result(frame)
            if _is_kept(v, keyframe.features, config):
                tmap.frames[fid] = replace(tmap.frames[fid], node=keyframe_node)
                cand.link, last_good = v, cand
                kept += 1
            else:
                if last_good is not None:
                    # the last frame that still matched well becomes the next keyframe
                    prev = keyframe_node
                    start_keyframe(last_good, new_node(last_good, prev, last_good.link))
                    last_good = None
                    v = _verify_pair(keyframe.features, frame.features, config.match)
                if _is_kept(v, keyframe.features, config):
                    tmap.frames[fid] = replace(tmap.frames[fid], node=keyframe_node)
                    cand.link, last_good = v, cand
                    kept += 1
                else:
                    prev = keyframe_node
                    start_keyframe(cand, new_node(cand, prev, v))
                    last_good = None
        on_frame(frame)


# ============================================================================= driver
def build_map(
    source: str | Path | ImageSequence,
    config: BuildConfig | None = None,
    camera: CameraIntrinsics | None = None,
    *,
    base: TopoMap | None = None,
    every: int = 1,
    on_progress: Callable[[BuildProgress], None] | None = None,
    executor: Executor | None = None,
) -> TopoMap:
    """Build a map from an image sequence, or extend ``base`` with a new sequence (``--append``).

    ``source``: image folder, video, list file, ROS bag or an :class:`ImageSequence`; ``config``:
    defaults to :class:`BuildConfig` (for ``base`` the map's own config is used); ``camera``:
    intrinsics of the *input* images (default: the source's own, e.g. a bag's CameraInfo, else
    :meth:`CameraIntrinsics.default`); ``executor``: where the per-frame and per-pair work runs
    (default: this process; see :mod:`topomap.parallel` — the map is the same with any). Unreadable
    frames are skipped, logged and recorded. Returns the map; ``map.sequences[-1]`` summarises this run.
    """
    t0 = time.perf_counter()
    executor = executor or InlineExecutor()
    seq = source if isinstance(source, ImageSequence) else open_sequence(source, every)
    if base is not None:
        if config is not None and config.features.kind != base.config.features.kind:
            raise ConfigError(
                f"the map uses {base.config.features.kind} features; cannot append a sequence with {config.features.kind}"
            )
        config = base.config
        if camera is not None:
            log.warning("--camera ignored when appending: the map's own intrinsics are used")
    elif camera is None:
        camera = seq.camera  # the source's own intrinsics (a bag's CameraInfo), if any
    config = config or BuildConfig()
    detector(config.features.kind)  # fail early on an unknown feature type
    tmap = base if base is not None else TopoMap(camera=CameraIntrinsics(1.0, 1.0, 0.0, 0.0), config=config)
    sequence_id = len(tmap.sequences)
    first_node = tmap.next_node_id()
    first_frame = len(tmap.frames)
    total = len(seq)
    skipped: list[tuple[str, str]] = []
    input_size: list[tuple[int, int] | None] = [None]
    # (x, y): verify(x, y) of the new edges, inliers only (_for_motion), for the motion stage
    verified: dict[tuple[int, int], Verification] = {}
    spill = Spill()  # the new keyframes' features and images wait on disk until the map is saved

    # the first readable frame (read here) fixes the working size of a new map
    head_frames, first = _first_readable(iter(seq), config)
    if base is not None:
        work_size = tmap.working_size
    elif first is not None:
        h, w = first.image.shape
        work_size = working_size(w, h, config.features.resize_max_px, config.features.upscale_min_px,
                                 config.features.max_upscale)
        cam_in = camera.fitted_to(w, h) if camera is not None else CameraIntrinsics.default(w, h)
        tmap.camera = cam_in.fitted_to(*work_size)
    else:
        work_size = None

    def new_node(c: _Candidate, prev_node: int | None, link: Verification | None) -> int:
        nid = tmap.next_node_id()
        rec = tmap.frames[c.record]
        image_data = None
        if config.store_images:
            from topomap.store import encode_image

            image_data = spill.put_bytes(encode_image(c.image, config.image_format, config.image_quality))
        tmap.add_node(
            Node(
                id=nid, sequence=sequence_id, frame_id=rec.id, source=rec.source, features=spill.put_features(c.features),
                thumbnail=make_thumbnail(c.image, config.thumbnail_px), image_data=image_data,
                descriptor=thumbnail_descriptor(c.image, descriptor_size(*work_size), DESCRIPTOR_PATCH),
            )
        )
        tmap.frames[c.record] = replace(rec, node=nid)
        if prev_node is not None and prev_node >= 0:
            v = link
            tmap.add_edge(Edge(prev_node, nid, EdgeKind.SEQUENTIAL, v.inliers if v else 0,
                               v.similarity if v else 0.0, v.flow_px if v else 0.0))
            if v is not None:
                verified[(prev_node, nid)] = _for_motion(v)
        return nid

    def on_frame(f: PreparedFrame) -> None:
        if f.status != "ok":
            if f.missing and executor.remote and _path_of(seq, f.index).is_file():
                raise ClusterError(
                    f"a Dask worker cannot read {_path_of(seq, f.index)} ({f.reason}); every worker must see the "
                    "images at the same path as this machine (a shared file system), or build without --scheduler"
                )
            skipped.append((f.name, f.reason or f.status))
            log.warning("skipped %s: %s", f.name, f.reason)
        elif input_size[0] is None:
            input_size[0] = f.input_size
        elif f.input_size != input_size[0]:
            log.warning("%s is %dx%d, the sequence %dx%d: resized to the map's working size", f.name, *f.input_size,
                        *input_size[0])
        _report(on_progress, "frames", f.index + 1, total, tmap)

    def prepared() -> Iterator[PreparedFrame]:
        for f in head_frames:  # unreadable or too small, before the first readable frame
            yield _skipped_frame(f)
        if first is None:
            return
        if base is None:
            yield prepare_frame(FrameTask(first.index, first.name, None, first.image, work_size, config.features))
            start = first.index + 1
        else:
            start = first.index
        yield from executor.map(prepare_frame, _frame_tasks(seq, work_size, config, start), window=4 * executor.workers)

    _select_keyframes(prepared(), tmap, config, sequence_id, executor, new_node, on_frame)

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
    build_index(tmap, on_progress, executor=executor)
    loops = _close_loops(tmap, new_ids, config, on_progress, executor=executor, verified=verified)
    aligned = 0
    if base is not None and config.align_min_confidence is not None:
        from topomap.alignment import align_experience  # imports the localizer: only an --append needs it

        links = align_experience(tmap, new_ids, config.align_min_confidence, seed=config.seed,
                                 on_progress=lambda done, total: _report(on_progress, "align", done, total, tmap))
        tmap.set_aligned_links(tmap.aligned_links() + links)
        aligned = len(links)
    _report(on_progress, "motion", 0, 1, tmap)
    annotate_edges(tmap, executor=executor, verified=verified)  # the keyframe pairs' geometry, read by the navigator
    verified.clear()
    _report(on_progress, "motion", 1, 1, tmap)
    calibrate(tmap, on_progress, executor=executor)
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
            "aligned_links_added": aligned,
            "seconds": round(time.perf_counter() - t0, 3),
            "input_size": list(input_size[0]) if input_size[0] else None,
        }
    )
    return tmap


def _path_of(seq: ImageSequence, index: int) -> Path:
    paths = seq.paths
    return paths[index] if paths is not None and 0 <= index < len(paths) else Path(seq.source)


def _skipped_frame(frame) -> PreparedFrame:
    """A frame read here that cannot be used (unreadable, or smaller than MIN_IMAGE_PX)."""
    if frame.image is None:
        return PreparedFrame(frame.index, frame.name, "unreadable", frame.error or "unreadable")
    h, w = frame.image.shape
    reason = f"{w}x{h} px is too small; images need at least {MIN_IMAGE_PX} px on each side"
    return PreparedFrame(frame.index, frame.name, "too small", reason, input_size=(w, h))


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


# ============================================================================= stage: index
def build_index(tmap: TopoMap, on_progress: Callable[[BuildProgress], None] | None = None, *,
                executor: Executor | None = None) -> BowIndex | None:
    """(Re)build the map's place-recognition index from its nodes' features (``topomap index``).

    The vocabulary is trained on the map's own keyframe descriptors (seeded k-means; the clusters
    of each level after the first are split in parallel on ``executor``). A map whose keyframes
    hold almost no features gets no index (``None``).
    """
    _report(on_progress, "index", 0, 1, tmap)
    index_global_descriptors(tmap)
    feats = {n.id: n.features for n in tmap.nodes.values()}
    desc = [_LazyDescriptors(f) for f in feats.values() if len(f)]  # read when sampled, not all at once
    total = sum(len(d) for d in desc)
    if total < MIN_INDEX_DESCRIPTORS:
        tmap.index = None
        return None
    cfg = tmap.config
    mapper = None
    if executor is not None and executor.workers > 1:
        def mapper(fn, items):
            return executor.map(fn, items, window=2 * executor.workers)
    voc = Vocabulary.train(desc, cfg.features.kind, vocabulary_size(total, cfg.vocabulary_words), cfg.seed,
                           mapper=mapper)
    tmap.index = BowIndex.build(voc, feats)
    _report(on_progress, "index", 1, 1, tmap)
    return tmap.index


class _LazyDescriptors:
    """A node's descriptors, read only when made an array (a fresh build's are on disk:
    :mod:`topomap.spill`); its length needs no read."""

    __slots__ = ("features",)

    def __init__(self, features: Features):
        self.features = features

    def __len__(self) -> int:
        return len(self.features)

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        return np.asarray(self.features.descriptors, dtype)


def calibrate(tmap: TopoMap, on_progress: Callable[[BuildProgress], None] | None = None, *,
              executor: Executor | None = None) -> Calibration | None:
    """Fit the map's localization calibration (:func:`topomap.self_supervision.calibrate_map`, its
    queries on ``executor``) when its config asks for one; a map that cannot be calibrated keeps none
    (logged) and localizes with raw confidences."""
    cfg = tmap.config.calibration
    tmap.meta.pop(CALIBRATION_KEY, None)  # a calibration of the map before this build is stale
    if not cfg.enabled or len(tmap.nodes) < cfg.min_nodes:
        return None
    _report(on_progress, "calibrate", 0, 1, tmap)
    try:
        cal = calibrate_map(tmap, queries=cfg.queries, seed=tmap.config.seed, executor=executor)
    except CalibrationError as e:
        log.warning("%s", e)
        return None
    _report(on_progress, "calibrate", 1, 1, tmap)
    return cal


def index_global_descriptors(tmap: TopoMap) -> GlobalDescriptors:
    """The whole-image (HOG) descriptor of every node from its thumbnail, kept in the map's arrays."""
    g = GlobalDescriptors.from_thumbnails({n.id: n.thumbnail for n in tmap.nodes.values()})
    tmap.arrays.update(g.to_arrays())
    tmap.meta["global_descriptor"] = g.to_meta()
    return g


# ============================================================================= stage: loops
def _loop_candidates(tmap: TopoMap, new_ids: list[int], cfg: BuildConfig, seq_adj: dict[int, list[int]]
                     ) -> Iterator[tuple[int, list[tuple[int, int]]]]:
    """Per new node (in id order): the pairs its appearance shortlist proposes for verification,
    each pair once over the whole stage, none already joined by an edge (``seq_adj``: the map's
    sequential adjacency, :func:`_sequential_adjacency`)."""
    index: BowIndex = tmap.index
    tested: set[tuple[int, int]] = set()
    all_ids = set(tmap.nodes)
    by_sequence: dict[int, set[int]] = {}
    for n in tmap.nodes.values():
        by_sequence.setdefault(n.sequence, set()).add(n.id)
    existing = set(tmap.edges)
    for nid in new_ids:
        node = tmap.nodes[nid]
        pairs: list[tuple[int, int]] = []
        if len(node.features) >= cfg.match.min_inliers:
            near = _within_steps(seq_adj, nid, cfg.loop_min_separation)
            words = index.words_of_features(nid)  # stored at indexing: no need to quantise again
            scores = index.scores(node.features, None if words is None else words.astype(np.int64))
            own = by_sequence[node.sequence]
            candidates = [(cid, score) for cid, score in index.top_k(scores, cfg.loop_shortlist_k, near | (all_ids - own))
                          if _camera_left(index, scores, nid, cid, own, cfg.loop_revisit_ratio)]
            if len(own) < len(all_ids):
                candidates += index.top_k(scores, cfg.loop_shortlist_k, own)
            for cid, score in candidates:
                pair = (min(nid, cid), max(nid, cid))
                if score <= 0 or pair in tested or pair in existing:
                    continue
                tested.add(pair)
                pairs.append((nid, cid))
        yield nid, pairs


def _camera_left(index: BowIndex, scores: np.ndarray, nid: int, cid: int, own: set[int], ratio: float | None) -> bool:
    """Whether the camera left node ``nid``'s place between it and ``cid`` (same sequence; ids follow
    the chain): some keyframe between scores under ``ratio`` times ``cid``'s score against ``nid``."""
    if ratio is None:
        return True
    between = [n for n in range(min(nid, cid) + 1, max(nid, cid)) if n in own]
    if not between:
        return True
    return bool(scores[index.row_indices(between)].min() < ratio * scores[index.row_indices([cid])[0]])


def _close_loops(tmap: TopoMap, new_ids: list[int], cfg: BuildConfig, on_progress, *,
                 executor: Executor | None = None, verified: dict | None = None) -> int:
    """The loops stage: verify the appearance shortlist of every new node (pairs in parallel on
    ``executor``, results in order); add ``loop`` edges, their verifications to ``verified``
    (``(x, y): verify(x, y)``, inliers only: :func:`_for_motion`). Returns how many. Shortlists are
    made as the verifications ask for work (a few nodes ahead), not all at once."""
    if tmap.index is None or len(tmap.nodes) < 3:
        return 0
    executor = executor or InlineExecutor()
    # one entry per pair in submission order, and (nid, None, None, True) for nodes without pairs
    order: deque[tuple[int, int | None, int | None, bool]] = deque()
    seq_adj = _sequential_adjacency(tmap)  # loop edges do not change it: one for the whole stage
    horizon = tmap.camera.fitted_to(*tmap.working_size).cy  # the centre row of the keyframes [px]

    def tasks():
        for nid, pairs in _loop_candidates(tmap, new_ids, cfg, seq_adj):
            if not pairs:
                order.append((nid, None, None, True))
            for j, (a, b) in enumerate(pairs):
                order.append((nid, a, b, j == len(pairs) - 1))
                yield tmap.nodes[a].features, tmap.nodes[b].features, cfg.match

    added = done = 0

    def node_done() -> None:
        nonlocal done
        done += 1
        _report(on_progress, "loops", done, len(new_ids), tmap)

    def nodes_without_pairs() -> None:
        while order and order[0][1] is None:
            order.popleft()
            node_done()

    accepted: list[tuple[int, int, Verification]] = []  # the current node's verified candidates
    for v in executor.map(_verify_task, tasks(), window=4 * executor.workers):
        nodes_without_pairs()
        nid, a, b, last = order.popleft()
        if (v.inliers >= cfg.loop_min_inliers and v.inlier_ratio >= cfg.loop_min_inlier_ratio
                and _off_floor_inliers(tmap, a, b, v, horizon) >= cfg.loop_min_off_floor_inliers):
            accepted.append((a, b, v))
        if last:
            for a, b, v in _best_per_visit(nid, accepted, seq_adj, cfg):
                tmap.add_edge(Edge(a, b, EdgeKind.LOOP, v.inliers, v.similarity, v.flow_px))
                if verified is not None:
                    verified[(a, b)] = _for_motion(v)
                added += 1
            accepted = []
            node_done()
    nodes_without_pairs()
    return added


def _off_floor_inliers(tmap: TopoMap, a: int, b: int, v: Verification, horizon_px: float) -> int:
    """Inliers of ``v`` (node ``a`` to node ``b``) above row ``horizon_px`` in both keyframes."""
    m = v.inlier_matches
    ya = tmap.nodes[a].features.keypoints[m.ia, 1]
    yb = tmap.nodes[b].features.keypoints[m.ib, 1]
    return int(np.count_nonzero((ya < horizon_px) & (yb < horizon_px)))


def _sequential_adjacency(tmap: TopoMap) -> dict[int, list[int]]:
    adj: dict[int, list[int]] = {}
    for e in tmap.edges.values():
        if e.kind is EdgeKind.SEQUENTIAL:
            adj.setdefault(e.a, []).append(e.b)
            adj.setdefault(e.b, []).append(e.a)
    return adj


def _best_per_visit(nid: int, accepted: list[tuple[int, int, Verification]], seq_adj: dict[int, list[int]],
                    cfg: BuildConfig) -> list[tuple[int, int, Verification]]:
    """The loop edges node ``nid`` keeps of its verified candidates ``(a, b, verification)``: the
    ``loop_edges_per_visit`` best (most inliers, then lowest id) of each visit, a visit being the
    candidates joined by chains of fewer than ``loop_min_separation`` sequential steps."""
    if cfg.loop_edges_per_visit == 0 or len(accepted) <= 1:
        return accepted
    other = {(b if a == nid else a): i for i, (a, b, _) in enumerate(accepted)}
    visits: list[list[int]] = []
    seen: set[int] = set()
    for c in sorted(other):
        if c in seen:
            continue
        visit, frontier = [], [c]  # flood through the candidates within reach of each other
        seen.add(c)
        while frontier:
            x = frontier.pop()
            visit.append(x)
            reach = _within_steps(seq_adj, x, cfg.loop_min_separation)
            for y in sorted(reach & other.keys() - seen):
                seen.add(y)
                frontier.append(y)
        visits.append(visit)
    keep: list[int] = []
    for visit in visits:
        ranked = sorted(visit, key=lambda c: (-accepted[other[c]][2].inliers, c))
        keep.extend(other[c] for c in ranked[: cfg.loop_edges_per_visit])
    return [accepted[i] for i in sorted(keep)]


def _within_steps(adj: dict[int, list[int]], nid: int, steps: int) -> set[int]:
    """Nodes reachable from ``nid`` in fewer than ``steps`` edges of ``adj`` (``nid`` included)."""
    seen, frontier = {nid}, [nid]
    for _ in range(max(0, steps - 1)):
        frontier = [m for n in frontier for m in adj.get(n, []) if m not in seen]
        seen.update(frontier)
    return seen
