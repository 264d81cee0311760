"""topomap.viz.animation and topomap.viz.overlay: the camera animation is at least 640 px wide,
shows both images with the matches and legible status text, plays at the robot's pace, and an MP4
is written when imageio's ffmpeg plugin is there (issue 18)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from PIL import Image

from topomap.groundtruth import read_poses
from topomap.navigate import EventKind
from topomap.sim.episode import run_episode
from topomap.sim.world import load_world
from topomap.store import load_map
from topomap.viz.animation import CameraAnimation, mp4_available, render_panel
from topomap.viz.overlay import StepMatches, status_lines, step_matches


def test_render_panel_layout_matches_and_text():
    rng = np.random.default_rng(0)
    cam = rng.integers(0, 256, (240, 320, 3)).astype(np.uint8)
    key = rng.integers(0, 256, (360, 480)).astype(np.uint8)
    cur = np.array([[100.0, 100.0], [200.0, 50.0], [300.0, 300.0]], np.float32)
    m = StepMatches(cur, cur + 10, np.array([True, True, False]), (480, 360))
    for width in (640, 960):
        f = render_panel(cam, key, m, ["line one", "line two"], width_px=width, event=("arrived", "arrived at node 3"))
        view_h = int(round(width / 2 * 240 / 320))
        assert f.shape[1] == width and f.shape[0] > view_h + 3 * width // 44 and f.dtype == np.uint8
        band = f[view_h:]
        # text: the band below the images holds bright glyph pixels on its dark background
        assert (band > 200).mean() > 0.005 and np.median(band) < 40
        # the inlier matches are drawn in green across both views, the outlier as a red dot on the left
        s = width / 2 / 480
        x, y = int(round(100 * s)), int(round(100 * s))
        assert tuple(f[y, x]) == (60, 220, 90)
        xo, yo = int(round(300 * s)), int(round(300 * s))
        assert tuple(f[yo, xo]) == (235, 70, 60)
        xr = int(round(110 * s)) + width // 2
        assert tuple(f[int(round(110 * s)), xr]) == (60, 220, 90)


@pytest.fixture(scope="module")
def recorded(short_run):
    """(map, events of a two-hop episode, CameraAnimation of it) on the short run's map."""
    m = load_map(short_run["map"], images=True)
    world = load_world(short_run["teach"] / "world.json")
    poses = read_poses(short_run["teach"] / "poses.csv")
    events = []
    anim = CameraAnimation(m, every=2)

    def listen(ev):
        events.append(ev)
        anim(ev)

    r = run_episode(m, world, 2, poses, start_node=0, on_event=listen)
    assert r.status == "arrived"
    return m, events, anim


@pytest.mark.slow
def test_step_events_carry_the_matches_the_servo_used(recorded):
    m, events, _ = recorded
    steps = [ev for ev in events if ev.kind is EventKind.STEP]
    assert steps and all(ev.matches is not None for ev in steps)
    for ev in steps:
        cur, goal = ev.matches
        assert cur.shape == goal.shape and cur.shape[1] == 2 and len(cur) == ev.servo.pose.n_matches
        sm = step_matches(m, ev)
        assert int(sm.inlier.sum()) == ev.servo.inliers or ev.servo.status.value == "lost"
        # the subgoal-side pixels are keypoints of the subgoal's keyframe
        kp = m.nodes[ev.subgoal].features.keypoints
        assert all(np.isclose(kp, p).all(axis=1).any() for p in goal[:5])
    lines = status_lines(steps[0], step_matches(m, steps[0]))
    assert f"subgoal node {steps[0].subgoal}" in lines[0] and "estimated distance" in lines[1] and "command" in lines[2]


@pytest.mark.slow
def test_gif_is_wide_real_time_and_mp4_when_available(recorded, tmp_path):
    _, events, anim = recorded
    steps = [ev for ev in events if ev.kind is EventKind.STEP]
    instants = sorted({ev.time_s for ev in steps})  # a subgoal switch repeats a step at the same instant
    assert len(instants) < len(steps)
    # every second instant, evenly spaced in robot time
    assert len(anim.shots) == math.ceil(len(instants) / 2)
    assert np.allclose(np.diff([s.time_s for s in anim.shots]), 0.2) and anim.step_s == pytest.approx(0.2)
    gif = anim.write_gif(tmp_path / "camera.gif")
    with Image.open(gif) as im:
        assert im.size[0] >= 640
        frames = im.n_frames
        durations = []
        for k in range(frames):
            im.seek(k)
            durations.append(im.info["duration"])
    # real-time pace: the GIF lasts as long as the run it shows (within one frame)
    robot_s = steps[-1].time_s - steps[0].time_s
    assert abs(sum(durations) / 1000 - robot_s) <= max(durations) / 1000 + 1e-9  # exactly one frame off is within
    assert set(durations) == {400}  # 2.5 frames per second
    video = anim.write_mp4(tmp_path / "camera.mp4")
    if not mp4_available():
        assert video is None
        pytest.skip("imageio-ffmpeg (the viz extra) is not installed: no MP4")
    import imageio.v2 as imageio

    with imageio.get_reader(video) as r:
        meta = r.get_meta_data()
        first = r.get_data(0)
        n = r.count_frames()
    assert meta["fps"] == pytest.approx(5.0) and first.shape[1] == 960 and first.shape[0] % 16 == 0
    assert n == len(anim.shots)


@pytest.mark.slow
def test_recorded_run_writes_gif_and_mp4(short_run):
    rec = short_run["record"]
    with Image.open(rec / "camera.gif") as im:
        assert im.size[0] >= 640 and im.n_frames >= 5
    assert (rec / "camera.mp4").is_file() == mp4_available()
    events = [json.loads(line) for line in (rec / "events.jsonl").read_text().splitlines()]
    assert events[-1]["kind"] == "arrived"
