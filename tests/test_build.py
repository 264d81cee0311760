"""topomap.build: keyframes, frame assignment, sequential and loop edges, --append, bad frames;
the acceptance checks of issue 2 on castle-p30 and corridor/ref."""

from __future__ import annotations

import csv
import dataclasses
import logging
import shutil

import cv2
import networkx as nx
import numpy as np
import pytest
from conftest import castle_map_file, corridor_map_file, dataset, walk_map_file
from map_synth import FAST, FRAME_SIZE, out_and_back_x, scene, sequence, window, write_sequence, write_video

import topomap.build as build_mod
from topomap.build import MIN_IMAGE_PX, BuildProgress, build_index, build_map
from topomap.camera import CameraIntrinsics, load_camera
from topomap.config import BuildConfig, CalibrationConfig, FeatureConfig
from topomap.errors import ConfigError, DatasetError
from topomap.features import extract
from topomap.graph import EdgeKind, TopoMap
from topomap.images import open_sequence
from topomap.matching import verify
from topomap.store import load_map


def snapshot(m: TopoMap) -> tuple:
    """Everything that must not change between two builds of the same input."""
    nodes = [(n.id, n.sequence, n.frame_id, n.source, n.features.keypoints.tobytes(), n.features.descriptors.tobytes())
             for n in sorted(m.nodes.values(), key=lambda n: n.id)]
    edges = [(e.a, e.b, e.kind, e.inliers, e.similarity, e.flow_px) for e in sorted(m.edges.values(), key=lambda e: e.key)]
    frames = [(f.id, f.source, f.node, f.status) for f in m.frames]
    return nodes, edges, frames


def nearest_keyframes(m: TopoMap) -> dict[int, int]:
    """Frame id -> the node of its sequence's keyframe nearest to it by frame index (ties: the
    earlier keyframe), for every frame with status ok and a node."""
    keys: dict[int, list[tuple[int, int]]] = {}
    for n in m.nodes.values():
        keys.setdefault(n.sequence, []).append((m.frames[n.frame_id].index, n.id))
    return {f.id: min(keys[f.sequence], key=lambda k: (abs(k[0] - f.index), k[0]))[1]
            for f in m.frames if f.status == "ok" and f.node is not None}


def consecutive_nodes_joined(m: TopoMap, sequence: int = 0) -> bool:
    ids = sorted(n.id for n in m.nodes.values() if n.sequence == sequence)
    return all(m.edge(a, b) is not None and m.edge(a, b).kind is EdgeKind.SEQUENTIAL for a, b in zip(ids, ids[1:]))


# ----------------------------------------------------------------------------- synthetic walk
@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    """(folder, x positions, map) of the synthetic out-and-back walk: the session's one build of it
    (shared with test_agreement.py), read back from its file."""
    folder, path = walk_map_file(tmp_path_factory)
    return folder, out_and_back_x(), load_map(path)


def test_keyframes_and_frame_assignment(walk):
    folder, xs, m = walk
    assert 3 <= len(m.nodes) < len(xs)
    assert len(m.frames) == len(xs) and all(f.status == "ok" and f.node is not None for f in m.frames)
    for n in m.nodes.values():
        assert m.frames[n.frame_id].node == n.id and m.frames[n.frame_id].source == n.source
    # nodes follow the input order, and so do the frames they represent
    assert [m.frames[n.frame_id].index for n in sorted(m.nodes.values(), key=lambda n: n.id)] == sorted(
        m.frames[n.frame_id].index for n in m.nodes.values())
    assert [f.node for f in m.frames] == sorted(f.node for f in m.frames)


def test_a_frame_is_represented_by_the_nearest_keyframe(tmp_path):
    """A new keyframe is the last frame that still matched the previous one: the frames just before
    it are nearer to it than to the keyframe they were tracked against, and it represents them."""
    write_sequence(tmp_path, sequence(16, step_px=15))
    m = build_map(tmp_path, FAST)
    assert [m.frames[n.frame_id].index for n in sorted(m.nodes.values(), key=lambda n: n.id)] == [0, 4, 8, 12]
    # 1, 2 (a tie: the keyframe tracked against) with keyframe 0; 3 with keyframe 4, one frame away
    assert [f.node for f in m.frames] == [0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2, 3, 3, 3, 3, 3]
    assert {f.id: f.node for f in m.frames} == nearest_keyframes(m)
    for frame in open_sequence(tmp_path):  # the later keyframe verifies the frames it takes over
        v = verify(m.nodes[m.frames[frame.index].node].features, extract(frame.image, m.config.features), m.config.match)
        assert v.inliers >= m.config.keyframe_min_inliers, (frame.name, v.inliers)


def test_flow_limit_starts_keyframes(walk):
    """Frames sliding ~19% of the width each keep enough matches, but servoing across more than
    ``keyframe_max_flow`` of the image is not wanted: without the limit the walk thins out."""
    folder, xs, m = walk
    loose = build_map(folder, dataclasses.replace(FAST, keyframe_max_flow=1.0))
    assert 3 <= len(loose.nodes) < len(xs) // 2 < len(m.nodes)
    limit = FAST.keyframe_max_flow * m.camera.width
    seq = [e for e in m.edges.values() if e.kind is EdgeKind.SEQUENTIAL]
    assert np.median([e.flow_px for e in seq]) <= 1.5 * limit


def test_each_frame_verifies_against_its_node(walk):
    """A frame's node is a keyframe it shares enough verified matches with (docs/theory.md section 4)."""
    folder, xs, m = walk
    cfg = m.config
    seq = open_sequence(folder)
    for frame in seq:
        node = m.nodes[m.frames[frame.index].node]
        if node.frame_id == frame.index:
            continue
        v = verify(node.features, extract(frame.image, cfg.features), cfg.match)
        assert v.inliers >= cfg.keyframe_min_inliers, (frame.name, node.id, v.inliers)


def test_sequential_edges_keep_servoable_overlap(walk):
    _, _, m = walk
    assert consecutive_nodes_joined(m)
    seq = [e for e in m.edges.values() if e.kind is EdgeKind.SEQUENTIAL]
    assert len(seq) == len(m.nodes) - 1
    assert all(e.inliers >= m.config.keyframe_min_inliers and 0 < e.similarity <= 1 for e in seq)


def test_loop_edges_join_views_of_the_same_place(walk):
    _, xs, m = walk
    loops = [e for e in m.edges.values() if e.kind is EdgeKind.LOOP]
    assert loops, "the way back should close loops with the way out"
    x_of = {n.id: xs[n.frame_id] for n in m.nodes.values()}
    width = FRAME_SIZE[0]
    for e in m.edges.values():  # no false edge: the two keyframes' windows overlap
        assert abs(x_of[e.a] - x_of[e.b]) < 0.8 * width, (e, x_of[e.a], x_of[e.b])
        assert e.inliers >= m.config.match.min_inliers
    for e in loops:
        assert e.inliers >= m.config.loop_min_inliers
    # closing the loop: the first and the last node (same place) are at most 2 edges apart
    ids = sorted(m.nodes)
    assert nx.shortest_path_length(m.graph, ids[0], ids[-1]) <= 2


#: RTAB-Map-like loop closures: one per visit, and within a sequence only after the camera left
SPARSE_LOOPS = dataclasses.replace(FAST, loop_edges_per_visit=1, loop_revisit_ratio=0.5)


@pytest.mark.slow  # builds one or more maps end to end (~8-30 s)
def test_a_walk_that_never_comes_back_closes_no_loop(tmp_path):
    """Sliding one way along a wall, keyframes 3-7 apart still share the view (like a corridor's far
    end); joining them would be a shortcut, not a loop: the camera never left, every keyframe between
    shows the place. Before the revisit test this walk had 114 loop edges."""
    write_sequence(tmp_path, sequence(n=44, step_px=40))
    m = build_map(tmp_path, SPARSE_LOOPS)
    assert len(m.nodes) > 20
    assert [e for e in m.edges.values() if e.kind is EdgeKind.LOOP] == []
    dense = build_map(tmp_path, FAST)  # the default keeps every verified candidate
    assert sum(e.kind is EdgeKind.LOOP for e in dense.edges.values()) > 20


def _tiled_floor_walk(n: int = 30, step_px: int = 40, period_px: int = 240) -> list[np.ndarray]:
    """A camera sliding along a plain wall over a floor whose tiles repeat every ``period_px``: the
    upper half of each frame is blank paint, the lower half a window over the periodic floor."""
    w, h = FRAME_SIZE
    tile = scene(5, width=period_px, height=h // 2)
    copies = (n * step_px + w) // period_px + 2
    strip = np.tile(tile, (1, copies))
    rng = np.random.default_rng(6)
    for k in range(copies):  # a few marks of its own on every tile (so that appearance can rank them)
        for _ in range(6):
            x, y = int(k * period_px + rng.integers(0, period_px)), int(rng.integers(0, h // 2))
            cv2.circle(strip, (x, y), int(rng.integers(3, 8)), int(rng.integers(0, 256)), -1)
    frames = []
    for i in range(n):
        f = np.full((h, w), 170, np.uint8)
        f[h // 2:] = strip[:, i * step_px: i * step_px + w]
        frames.append(f)
    return frames


@pytest.mark.slow  # builds one or more maps end to end (~8-30 s)
def test_a_repeating_floor_closes_no_loop(tmp_path):
    """Sliding one way over tiles that repeat, every sixth frame sees the floor it saw before: on the
    floor alone the views verify (aliased loop edges, like the simulated offices' 2-18 m ones), but
    the camera never came back. A loop closure needs inliers off the floor too."""
    write_sequence(tmp_path, _tiled_floor_walk(n=18))  # three tile periods: the floor comes round twice
    m = build_map(tmp_path, FAST)
    assert len(m.nodes) >= 5
    assert [e for e in m.edges.values() if e.kind is EdgeKind.LOOP] == []
    aliased = build_map(tmp_path, dataclasses.replace(FAST, loop_min_off_floor_inliers=0))
    assert sum(e.kind is EdgeKind.LOOP for e in aliased.edges.values()) > 0


def _loop_degrees(m) -> dict[int, int]:
    degree: dict[int, int] = {}
    for e in m.edges.values():
        if e.kind is EdgeKind.LOOP:
            degree[e.a] = degree.get(e.a, 0) + 1
            degree[e.b] = degree.get(e.b, 0) + 1
    return degree


def test_one_loop_edge_per_place_seen_again(walk):
    """With sparse loops the way back meets each place of the way out once: of a new node's verified
    candidates, one per visit (a run along the other pass's chain) becomes an edge — a ladder
    between the passes, not every keyframe of one pass joined to every keyframe of the other."""
    folder, _, dense = walk
    m = build_map(folder, SPARSE_LOOPS)
    out_pass = [n for n in sorted(m.nodes) if n < len(m.nodes) // 2]
    degree, dense_degree = _loop_degrees(m), _loop_degrees(dense)
    assert max(dense_degree.get(n, 0) for n in out_pass) >= 5  # the default: every verified candidate
    assert max(degree.get(n, 0) for n in out_pass) <= 3
    assert sum(1 for n in out_pass if degree.get(n, 0)) >= len(out_pass) - 3  # ... and still a ladder
    ids = sorted(m.nodes)
    assert nx.shortest_path_length(m.graph, ids[0], ids[-1]) <= 2  # the loop still closes


@pytest.mark.slow  # builds one or more maps end to end (~8-30 s)
def test_determinism(walk):
    folder, _, m = walk
    again = build_map(folder, FAST)
    assert snapshot(again) == snapshot(m)


def test_progress_and_sequence_summary(tmp_path):
    write_sequence(tmp_path, sequence(12))
    seen: list[BuildProgress] = []
    m = build_map(tmp_path, FAST, on_progress=seen.append)
    assert len(m.nodes) >= 3  # enough for loop closure to run
    stages = [p.stage for p in seen]
    n = len(m.nodes)
    assert stages[:12] == ["frames"] * 12 and stages[12:14] == ["index", "index"] and stages[14:14 + n] == ["loops"] * n
    assert stages[14 + n:] == ["motion", "motion"]  # FAST maps are too small to calibrate
    last = {p.stage: p for p in seen}
    assert (last["frames"].done, last["frames"].total, last["frames"].nodes) == (12, 12, len(m.nodes))
    assert (last["loops"].done, last["loops"].total, last["loops"].edges) == (len(m.nodes), len(m.nodes), len(m.edges))
    run = m.sequences[-1]
    assert run["frames"] == run["frames_read"] == 12 and run["frames_skipped"] == 0 and run["kind"] == "folder"
    assert run["nodes_added"] == len(m.nodes) and run["input_size"] == list(FRAME_SIZE)


# ----------------------------------------------------------------------------- --append
@pytest.mark.slow  # builds one or more maps end to end (~8-30 s)
def test_append_links_a_second_pass(tmp_path):
    tex = scene(2)
    xs = range(0, 480, 60)  # 8 frames a pass: several keyframes each, one frame width of wall
    out = [window(tex, x, y=40.0) for x in xs]
    rng = np.random.default_rng(9)  # the second pass: same places, other sensor noise, 20 px lower
    again = [np.clip(window(tex, x + 7, y=60.0) + rng.normal(0, 4, FRAME_SIZE[::-1]), 0, 255).astype(np.uint8)
             for x in xs]
    write_sequence(tmp_path / "a", out)
    write_sequence(tmp_path / "b", again)
    base = build_map(tmp_path / "a", FAST)
    n0, f0 = base.next_node_id(), len(base.frames)
    m = build_map(tmp_path / "b", base=base, camera=CameraIntrinsics.default(10, 10))
    assert m is base and len(m.sequences) == 2
    new = [n for n in m.nodes.values() if n.sequence == 1]
    assert new and min(n.id for n in new) == n0
    assert [f.id for f in m.frames[f0:]] == list(range(f0, f0 + len(again)))
    assert all(f.sequence == 1 and f.node in {n.id for n in new} for f in m.frames[f0:])
    links = [e for e in m.edges.values() if e.kind is EdgeKind.LOOP and (e.a < n0) != (e.b < n0)]
    assert links, "the second pass must be linked to the first by loop edges"
    assert len(m.components()) == 1 and consecutive_nodes_joined(m, 1)
    assert m.camera.source == "default" and m.working_size == FRAME_SIZE  # --camera ignored on append
    assert m.index is not None and len(m.index) == len(m.nodes)
    with pytest.raises(ConfigError, match="uses orb features; cannot append a sequence with sift"):
        build_map(tmp_path / "b", BuildConfig(features=FeatureConfig(kind="sift")), base=m)


# ----------------------------------------------------------------------------- bad frames
def test_unreadable_frames_are_skipped_and_counted(tmp_path, caplog):
    write_sequence(tmp_path, sequence(5), ext=".jpg")
    (tmp_path / "img1.jpg").write_bytes(b"")  # zero bytes
    data = (tmp_path / "img3.jpg").read_bytes()
    (tmp_path / "img3.jpg").write_bytes(data[: len(data) // 2])  # truncated
    (tmp_path / "img4.jpg").write_text("not really a jpeg")
    with caplog.at_level(logging.WARNING, logger="topomap"):
        m = build_map(tmp_path, FAST)
    assert [f.status for f in m.frames] == ["ok", "unreadable", "ok", "unreadable", "unreadable"]
    assert [f.node is None for f in m.frames] == [False, True, False, True, True]
    run = m.sequences[-1]
    assert run["frames_read"] == 2 and run["frames_skipped"] == 3
    assert [s["frame"] for s in run["skipped"]] == ["img1.jpg", "img3.jpg", "img4.jpg"]
    assert sum("skipped" in r.getMessage() for r in caplog.records) == 3


def test_only_unreadable_frames_is_an_error(tmp_path):
    (tmp_path / "a.png").write_bytes(b"")
    (tmp_path / "b.png").write_text("text")
    with pytest.raises(DatasetError, match=r"no usable image in .*a\.png: image a\.png is an empty file"):
        build_map(tmp_path, FAST)


def test_tiny_images_are_skipped(tmp_path):
    frames = sequence(3)
    write_sequence(tmp_path / "mixed", frames)
    cv2.imwrite(str(tmp_path / "mixed" / "img1.png"), frames[1][:16, :16])
    m = build_map(tmp_path / "mixed", FAST)
    assert [f.status for f in m.frames] == ["ok", "too small", "ok"]
    assert "16x16 px is too small" in m.sequences[-1]["skipped"][0]["reason"]
    cv2.imwrite(str(tmp_path / "tiny.png"), frames[0][:16, :16])
    with pytest.raises(DatasetError, match=f"no usable image.*16x16 px is too small.*{MIN_IMAGE_PX} px"):
        build_map(tmp_path / "tiny.png", FAST)


def test_small_but_usable_images_are_upscaled(tmp_path):
    small = [cv2.resize(f, (120, 90), interpolation=cv2.INTER_AREA) for f in sequence(4, step_px=30)]
    write_sequence(tmp_path, small)
    m = build_map(tmp_path, FAST)
    # enlarged towards 480 px, but by at most max_upscale (3x): 120x90 -> 360x270
    assert m.working_size == (360, 270) and all(f.node is not None for f in m.frames)
    assert m.camera.fx == pytest.approx(CameraIntrinsics.default(360, 270).fx)


def test_identical_frames_make_one_node(tmp_path):
    write_sequence(tmp_path, [sequence(1)[0]] * 5)
    m = build_map(tmp_path, FAST)
    assert len(m.nodes) == 1 and not m.edges and [f.node for f in m.frames] == [0] * 5


def test_featureless_frames_join_the_last_keyframe_with_features(tmp_path):
    """A turn facing blank paint: frames too plain to verify anything are no keyframes (no image
    could certify them as a goal); they are represented by the last view that had features."""
    frames = sequence(8, step_px=60)
    blank = np.full_like(frames[0], 128)
    write_sequence(tmp_path, frames[:4] + [blank] * 3 + frames[4:])
    m = build_map(tmp_path, FAST)
    assert all(len(n.features) >= FAST.match.min_inliers for n in m.nodes.values())
    assert all(f.node is not None for f in m.frames)
    # the blank frames join the node of the frame before them (its keyframe, or it became one); when
    # the next keyframe is made, the one past the midpoint (frame 6) moves to it, as any frame does
    before, after = m.frames[3].node, m.frames[7].node
    assert m.nodes[before].frame_id == 3 and m.nodes[after].frame_id == 7
    assert [f.node for f in m.frames[4:7]] == [before, before, after]
    assert {f.id: f.node for f in m.frames} == nearest_keyframes(m)
    assert consecutive_nodes_joined(m)


#: Nordland summer frames built by the appearance-only test: the first quarter of the 1200 (137 of
#: them under a verification's minimum of keypoints) makes the point in a quarter of the time.
NORDLAND_FRAMES = 300


@pytest.mark.slow
def test_an_appearance_only_sequence_keeps_its_low_feature_frames(tmp_path):
    """Nordland's 64x32 frames hold ~23 keypoints, a third of them under a verification's minimum:
    whole-image descriptors recognise them, so they stay places (the blank-paint rule is for maps of
    keypoints)."""
    for p in sorted((dataset("nordland-64x32") / "summer").glob("*.png"))[:NORDLAND_FRAMES]:
        shutil.copy(p, tmp_path / p.name)
    quick = dataclasses.replace(BuildConfig(), calibration=CalibrationConfig(enabled=False))  # not what is tested
    m = build_map(tmp_path, quick)
    low = [n for n in m.nodes.values() if len(n.features) < m.config.match.min_inliers]
    assert len(m.nodes) == NORDLAND_FRAMES and len(low) > 100


def test_single_image(tmp_path):
    cv2.imwrite(str(tmp_path / "one.png"), sequence(1)[0])
    m = build_map(tmp_path / "one.png", FAST)
    assert len(m.nodes) == 1 and len(m.frames) == 1 and not m.edges and m.sequences[-1]["kind"] == "image"


def test_interrupted_build_propagates(tmp_path, monkeypatch):
    write_sequence(tmp_path, sequence(4))

    def interrupt(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(build_mod, "_close_loops", interrupt)
    with pytest.raises(KeyboardInterrupt):
        build_map(tmp_path, FAST)


# ----------------------------------------------------------------------------- inputs, camera, index
def test_every_and_list_and_video_inputs(tmp_path):
    frames = sequence(8, step_px=30)
    write_sequence(tmp_path / "f", frames)
    half = build_map(tmp_path / "f", FAST, every=2)
    assert [f.source for f in half.frames] == ["img0.png", "img2.png", "img4.png", "img6.png"]
    (tmp_path / "list.txt").write_text("f/img7.png\nf/img1.png\n")
    listed = build_map(tmp_path / "list.txt", FAST)
    assert [f.source for f in listed.frames] == ["img7.png", "img1.png"]
    video = write_video(tmp_path / "v.avi", frames)
    vm = build_map(video, FAST, every=2)
    assert [f.source for f in vm.frames] == ["frame_000000", "frame_000002", "frame_000004", "frame_000006"]
    assert vm.sequences[-1]["kind"] == "video"


def test_default_camera_is_recorded(walk):
    _, _, m = walk
    assert m.camera == CameraIntrinsics.default(*FRAME_SIZE)
    assert m.camera.source == "default" and m.summary()["camera"]["source"] == "default"


def test_given_camera_is_fitted_to_the_working_size(tmp_path):
    write_sequence(tmp_path, [cv2.resize(f, (240, 180)) for f in sequence(2)])
    cam = CameraIntrinsics(200.0, 200.0, 119.5, 89.5, source="calib.yaml")  # size unknown: the input's
    m = build_map(tmp_path, FAST, cam)
    assert m.working_size == (480, 360)  # enlarged to 480 px
    assert (m.camera.fx, m.camera.cx, m.camera.cy, m.camera.source) == (400.0, 239.5, 179.5, "calib.yaml")
    shrunk = build_map(tmp_path, dataclasses.replace(FAST, features=dataclasses.replace(FAST.features, upscale_min_px=0,
                                                                                          resize_max_px=120)), cam)
    assert shrunk.working_size == (120, 90) and shrunk.camera.fx == 100.0


def test_build_index_is_reproducible(walk):
    _, _, m = walk
    old = m.index.to_arrays()
    copy = dataclasses.replace(m, index=None)
    idx = build_index(copy)
    new = idx.to_arrays()
    assert old.keys() == new.keys() and all(np.array_equal(old[k], new[k]) for k in old)
    bare = TopoMap(camera=m.camera, config=m.config)
    assert build_index(bare) is None and bare.index is None


# ----------------------------------------------------------------------------- real data (issue 2)
@pytest.fixture(scope="module")
def castle(tmp_path_factory):
    # the session's one castle build (shared with test_parallel.py), read back from its file
    return dataset("castle-p30"), load_map(castle_map_file(tmp_path_factory))


@pytest.fixture(scope="module")
def corridor(tmp_path_factory):
    # the session's one corridor build with the defaults (~30 s), read back from its file
    return load_map(corridor_map_file(tmp_path_factory))


def test_castle_closes_the_loop(castle):
    _, m = castle
    assert len(m.components()) == 1
    a, b = m.node_of_frame("0028.jpg"), m.node_of_frame("0002.jpg")
    assert a is not None and b is not None
    assert nx.shortest_path_length(m.graph, a, b) <= 2  # without closure: the whole loop apart
    assert m.edges_by_kind()["loop"] >= 1


def test_castle_has_no_false_edge(castle):
    root, m = castle
    with open(root / "covisibility.csv", newline="") as fh:
        relation = {frozenset((r["frame_a"], r["frame_b"])): r["relation"] for r in csv.DictReader(fh)}
    for e in m.edges.values():
        pair = frozenset((m.nodes[e.a].source, m.nodes[e.b].source))
        assert relation[pair] != "unrelated", (e, sorted(pair))


def test_castle_records_the_given_camera(castle):
    _, m = castle
    assert m.working_size == (768, 512) and m.camera.source == "K.txt"
    assert (m.camera.fx, m.camera.fy, m.camera.cx, m.camera.cy) == (689.87, 691.04, 380.1725, 251.7025)
    assert len(m.frames) == 30 and all(f.node is not None for f in m.frames)


@pytest.mark.slow  # builds one or more maps end to end (~8-30 s)
def test_castle_build_is_deterministic(castle):
    root, m = castle
    again = build_map(root / "images", camera=load_camera(root / "K.txt"))
    assert snapshot(again) == snapshot(m)


@pytest.mark.slow
def test_corridor_ref(corridor):
    m = corridor
    assert len(m.frames) == 111 and all(f.node is not None for f in m.frames)
    assert 1 < len(m.nodes) < len(m.frames)
    assert consecutive_nodes_joined(m)
    assert len(m.components()) == 1
    assert m.working_size == (480, 360) and m.camera.source == "default"
    # keyframe 15 (node 4) represents ref 14, one frame from it, not keyframe 12 two frames back
    assert {f.id: f.node for f in m.frames} == nearest_keyframes(m)
    assert m.node_of_frame("0000014.jpg") == m.node_of_frame("0000015.jpg") != m.node_of_frame("0000013.jpg")
