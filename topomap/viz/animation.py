"""The camera animation of a navigation run: what the robot saw beside what it servoed to.

Each frame puts the current camera view and the subgoal's keyframe side by side with the matched
features joined across (green: kept by the servo's pose, red dots: rejected), and under them the
status in plain text: time, servo status, subgoal and its place in the route, estimated distance and
heading, inliers, the command, and the latest event. :class:`CameraAnimation` listens to the
navigator's events (it never feeds anything back) and writes an animated GIF (always, with Pillow)
and an MP4 (through imageio's ffmpeg plugin, the ``viz`` extra, when installed), both played at
the robot's own pace: one second of the animation is one second of the run.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

from topomap.graph import TopoMap
from topomap.viz.overlay import StepMatches, keyframe_image, status_lines, step_matches

__all__ = ["CameraAnimation", "render_panel", "mp4_available"]

log = logging.getLogger(__name__)

#: Colours (RGB) of the drawing.
INLIER_RGB = (60, 220, 90)
OUTLIER_RGB = (235, 70, 60)
TEXT_RGB = (240, 240, 240)
STATUS_RGB = {"approaching": (240, 240, 240), "aligning": (255, 210, 80), "converged": (90, 230, 120),
              "lost": (255, 90, 80)}
EVENT_RGB = {"arrived": (90, 230, 120), "failed": (255, 90, 80), "timeout": (255, 90, 80), "lost": (255, 170, 60)}
#: Most match lines drawn per frame (evenly chosen): more hide the images.
MAX_LINES = 60
#: How long an event's message stays on screen [s].
EVENT_SHOWN_S = 4.0


@lru_cache(maxsize=8)
def _font(size_px: int):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size_px)  # Pillow's scalable built-in font (FreeType)
    except (TypeError, OSError):  # pragma: no cover - Pillow without FreeType: the bitmap font
        return ImageFont.load_default()


def _rgb(image: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(image, cv2.COLOR_GRAY2RGB) if image.ndim == 2 else image[:, :, :3]


def render_panel(camera_rgb: np.ndarray, keyframe: np.ndarray, matches: StepMatches, lines: list[str],
                 *, width_px: int = 960, status: str = "", event: tuple[str, str] | None = None,
                 labels: tuple[str, str] = ("camera", "subgoal keyframe")) -> np.ndarray:
    """One animation frame, ``(H, width_px, 3) uint8`` RGB: ``camera_rgb`` (the robot's image) and
    ``keyframe`` side by side, ``matches`` drawn across, ``lines`` of text below (the first in the
    colour of ``status``), then ``event = (kind, message)`` if given."""
    from PIL import Image, ImageDraw

    view_w = width_px // 2
    h0, w0 = camera_rgb.shape[:2]
    view_h = int(round(view_w * h0 / w0))
    cam = cv2.resize(_rgb(camera_rgb), (view_w, view_h), interpolation=cv2.INTER_AREA if w0 > view_w else cv2.INTER_LINEAR)
    key = cv2.resize(_rgb(keyframe), (view_w, view_h), interpolation=cv2.INTER_LINEAR)
    top = np.hstack([cam, key])
    # the matches, from working-resolution pixels to the views
    sx, sy = view_w / matches.size[0], view_h / matches.size[1]
    thick = max(1, width_px // 640)
    if len(matches):
        cur = matches.cur_px * (sx, sy)
        goal = matches.goal_px * (sx, sy) + (view_w, 0)
        for p in cur[~matches.inlier]:
            cv2.circle(top, (int(round(p[0])), int(round(p[1]))), 2 * thick, OUTLIER_RGB, -1, cv2.LINE_AA)
        ins = np.flatnonzero(matches.inlier)
        if len(ins) > MAX_LINES:
            ins = ins[np.linspace(0, len(ins) - 1, MAX_LINES).round().astype(int)]
        for i in ins:
            a, b = tuple(int(round(v)) for v in cur[i]), tuple(int(round(v)) for v in goal[i])
            cv2.line(top, a, b, INLIER_RGB, thick, cv2.LINE_AA)
            cv2.circle(top, a, 2 * thick, INLIER_RGB, -1, cv2.LINE_AA)
            cv2.circle(top, b, 2 * thick, INLIER_RGB, -1, cv2.LINE_AA)
    cv2.line(top, (view_w, 0), (view_w, view_h), (20, 20, 20), 2)
    font_px = max(14, width_px // 44)
    line_h = int(font_px * 1.35)
    n_lines = len(lines) + 1
    band = np.full((line_h * n_lines + font_px // 2, width_px, 3), 24, np.uint8)
    img = Image.fromarray(np.vstack([top, band]))
    draw = ImageDraw.Draw(img)
    font = _font(font_px)
    pad = max(4, font_px // 3)
    for x0, text in ((pad, labels[0]), (view_w + pad, labels[1])):
        box = draw.textbbox((x0, pad), text, font=font)
        draw.rectangle((box[0] - 3, box[1] - 2, box[2] + 3, box[3] + 2), fill=(0, 0, 0))
        draw.text((x0, pad), text, font=font, fill=TEXT_RGB)
    y = view_h + font_px // 4
    for k, text in enumerate(lines):
        draw.text((pad, y), text, font=font, fill=STATUS_RGB.get(status, TEXT_RGB) if k == 0 else TEXT_RGB)
        y += line_h
    if event is not None:
        draw.text((pad, y), event[1], font=font, fill=EVENT_RGB.get(event[0], (150, 200, 255)))
    return np.asarray(img)


def mp4_available() -> bool:
    """imageio's ffmpeg plugin (and its ffmpeg binary) is installed."""
    try:
        import imageio_ffmpeg

        imageio_ffmpeg.get_ffmpeg_exe()
    except (ImportError, RuntimeError, OSError):
        return False
    return True


@dataclass(frozen=True)
class _Shot:
    time_s: float
    jpeg: bytes  # the camera image, JPEG-compressed to bound memory over long runs
    subgoal: int
    status: str
    matches: StepMatches
    lines: tuple[str, ...]
    event: tuple[str, str] | None


class CameraAnimation:
    """Navigator event listener that records the camera animation of a run.

    ``tmap``: the map being navigated (keyframe images at the working resolution make the right half;
    maps loaded without images fall back to thumbnails); ``every``: keep every n-th control step;
    ``max_shots``: stop recording after this many (bounded memory; about 25 kB each).
    """

    def __init__(self, tmap: TopoMap, every: int = 1, max_shots: int = 9000):
        self.tmap = tmap
        self.every = max(1, int(every))
        self.max_shots = int(max_shots)
        self.shots: list[_Shot] = []
        self._steps = 0
        self._last_time: float | None = None
        self._event: tuple[float, str, str] | None = None

    def __call__(self, ev) -> None:
        from topomap.navigate import EventKind

        if ev.kind is not EventKind.STEP:
            self._event = (ev.time_s, ev.kind.value, f"{ev.time_s:6.1f} s  {ev.kind.value}: {ev.message}")
            return
        # a subgoal switch repeats the step at the same instant: it replaces that instant's shot, so
        # shots stay evenly spaced in robot time (real-time playback)
        again = self._last_time is not None and ev.time_s <= self._last_time
        self._last_time = ev.time_s
        if not again:
            self._steps += 1
        replace = again and bool(self.shots) and self.shots[-1].time_s == ev.time_s
        if ev.image is None or ev.subgoal is None:
            return
        if not replace and (again or (self._steps - 1) % self.every or len(self.shots) >= self.max_shots):
            return
        m = step_matches(self.tmap, ev)
        event = None
        if self._event is not None and ev.time_s - self._event[0] <= EVENT_SHOWN_S:
            event = self._event[1:]
        ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(_rgb(ev.image), cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 92])
        if replace:
            self.shots.pop()
        self.shots.append(_Shot(ev.time_s, jpg.tobytes(), int(ev.subgoal), ev.servo.status.value if ev.servo else "",
                                m, tuple(status_lines(ev, m)), event))

    # -- frames
    @property
    def step_s(self) -> float:
        """Robot time between two recorded shots [s] (the median, 0.1 s when unknown)."""
        if len(self.shots) < 2:
            return 0.1 * self.every
        return float(np.median(np.diff([s.time_s for s in self.shots])))

    def frame(self, k: int, width_px: int = 960) -> np.ndarray:
        """Shot ``k`` rendered ``width_px`` wide, ``(H, W, 3) uint8`` RGB."""
        s = self.shots[k]
        cam = cv2.cvtColor(cv2.imdecode(np.frombuffer(s.jpeg, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        return render_panel(cam, keyframe_image(self.tmap, s.subgoal), s.matches, list(s.lines), width_px=width_px,
                            status=s.status, event=s.event, labels=("camera", f"subgoal keyframe: node {s.subgoal}"))

    def _stride(self, max_fps: float) -> int:
        """Shots per frame so the frame rate stays at or below ``max_fps`` at real-time pace."""
        return max(1, int(math.ceil((1.0 / max_fps) / max(self.step_s, 1e-3) - 1e-9)))

    def write_gif(self, path: str | Path, width_px: int = 640, max_fps: float = 2.5, colors: int = 64) -> Path | None:
        """An animated GIF, real-time pace, at most ``max_fps`` frames per second and ``colors``
        palette entries (a GIF's size grows with both: see docs/navigation.md); None when nothing
        was recorded."""
        from PIL import Image

        if not self.shots:
            return None
        stride = self._stride(max_fps)
        duration_ms = int(round(1000 * stride * self.step_s))
        frames = [Image.fromarray(self.frame(k, width_px)).quantize(colors=colors, method=Image.Quantize.FASTOCTREE)
                  for k in range(0, len(self.shots), stride)]
        path = Path(path)
        frames[0].save(path, save_all=True, append_images=frames[1:], duration=duration_ms, loop=0, optimize=False)
        return path

    def write_mp4(self, path: str | Path, width_px: int = 960, max_fps: float = 30.0, crf: int = 28) -> Path | None:
        """An H.264 MP4 (``crf``: x264's constant quality, lower is better), real-time pace; None when
        imageio's ffmpeg plugin is missing or nothing was recorded."""
        if not self.shots or not mp4_available():
            return None
        import imageio.v2 as imageio

        stride = self._stride(max_fps)
        fps = 1.0 / (stride * self.step_s)
        path = Path(path)
        with imageio.get_writer(path, format="FFMPEG", mode="I", fps=fps, codec="libx264", quality=None,
                                pixelformat="yuv420p", macro_block_size=16, ffmpeg_log_level="error",
                                output_params=["-crf", str(crf), "-preset", "veryfast"]) as w:
            for k in range(0, len(self.shots), stride):
                f = self.frame(k, width_px)
                pad = (-f.shape[0]) % 16  # H.264 wants whole macroblocks: pad rather than let ffmpeg rescale
                w.append_data(np.vstack([f, np.full((pad, f.shape[1], 3), 24, np.uint8)]) if pad else f)
        return path
