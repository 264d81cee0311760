"""Seeded synthetic image sequences for the map tests (imported by tests/test_*.py).

A textured planar scene (random rectangles and ellipses at several scales, blurred, with noise) is
seen through a window that slides (and optionally zooms) across it, so tests get real, repeatable
keypoints without reading the big datasets. Everything derives from an explicit seed.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from topomap.config import BuildConfig, FeatureConfig

__all__ = ["scene", "window", "sequence", "out_and_back_x", "write_out_and_back", "write_sequence", "write_video",
           "FRAME_SIZE", "FAST", "SHORT_WALK_PX"]

#: (width, height) of the synthetic frames [px]; >= 480 so the build does not upscale them.
FRAME_SIZE = (480, 360)

#: Small, fast build settings for synthetic data (few features, a small vocabulary).
FAST = BuildConfig(features=FeatureConfig(max_features=500), vocabulary_words=64)


def scene(seed: int = 0, width: int = 2400, height: int = 480) -> np.ndarray:
    """A (height, width) uint8 texture: random shapes at several scales, blurred, plus mild noise."""
    rng = np.random.default_rng(seed)
    img = np.full((height, width), 128, np.uint8)
    for size, count in ((60, width * height // 9000), (25, width * height // 2500), (8, width * height // 700)):
        for _ in range(count):
            x, y = int(rng.integers(0, width)), int(rng.integers(0, height))
            a, b = (int(v) for v in rng.integers(size // 3 + 1, size + 1, 2))
            colour = int(rng.integers(0, 256))
            if rng.random() < 0.5:
                cv2.rectangle(img, (x - a, y - b), (x + a, y + b), colour, -1)
            else:
                cv2.ellipse(img, (x, y), (a, b), float(rng.uniform(0, 180)), 0, 360, colour, -1)
    img = cv2.GaussianBlur(img, (3, 3), 0.8)
    noise = rng.normal(0.0, 3.0, img.shape)
    return np.clip(img.astype(np.float64) + noise, 0, 255).astype(np.uint8)


def window(texture: np.ndarray, x: float, zoom: float = 1.0, y: float = 0.0, size: tuple[int, int] = FRAME_SIZE) -> np.ndarray:
    """The (h, w) view of ``texture`` whose top-left corner is ``(x, y)``, magnified ``zoom`` times."""
    w, h = size
    A = np.array([[zoom, 0.0, -zoom * x], [0.0, zoom, -zoom * y]])
    return cv2.warpAffine(texture, A, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def sequence(n: int = 12, step_px: float = 60.0, seed: int = 0, zoom_step: float = 0.0, start_px: float = 0.0,
             y: float = 40.0, noise_seed: int | None = None) -> list[np.ndarray]:
    """``n`` frames sliding ``step_px`` to the right per frame over ``scene(seed)`` (zoom grows by
    ``zoom_step`` per frame). ``noise_seed`` adds independent sensor noise (a "second pass")."""
    tex = scene(seed)
    frames = [window(tex, start_px + i * step_px, 1.0 + i * zoom_step, y) for i in range(n)]
    if noise_seed is not None:
        rng = np.random.default_rng(noise_seed)
        frames = [np.clip(f + rng.normal(0, 4.0, f.shape), 0, 255).astype(np.uint8) for f in frames]
    return frames


def write_sequence(folder: Path, frames: list[np.ndarray], stem: str = "img", ext: str = ".png") -> list[Path]:
    """Write frames as ``{stem}{i}{ext}`` (no zero padding: natural sort matters) into ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, f in enumerate(frames):
        p = folder / f"{stem}{i}{ext}"
        if not cv2.imwrite(str(p), f):
            raise RuntimeError(f"could not write {p}")
        paths.append(p)
    return paths


def write_video(path: Path, frames: list[np.ndarray], fps: float = 10.0) -> Path:
    """An MJPG .avi of the (grey) frames."""
    h, w = frames[0].shape[:2]
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h))
    if not vw.isOpened():
        raise RuntimeError("cv2.VideoWriter cannot write MJPG here")
    for f in frames:
        vw.write(cv2.cvtColor(f, cv2.COLOR_GRAY2BGR))
    vw.release()
    return path


def out_and_back_x(step_px: int = 60, length_px: int = 1000) -> list[float]:
    """Window positions of a walk right along the wall and back; the way back is offset 3 px so no
    frame repeats exactly (the revisit must be found by loop closure, not by identical images)."""
    out = list(range(0, length_px, step_px))
    back = list(range(length_px, -1, -step_px))
    return [float(x) for x in out] + [x + 3.0 for x in back]


#: Length [px] of the short out-and-back walk: 11 frames, 8 keyframes and still loop closures on
#: the way back, for tests that build the walk several times (the full walk: 34 frames, ~8 s a build).
SHORT_WALK_PX = 300


def write_out_and_back(folder: Path, seed: int = 0, length_px: int = 1000) -> list[float]:
    """Write the out-and-back walk over ``scene(seed)`` into ``folder``; returns each frame's x [px]."""
    tex = scene(seed)
    xs = out_and_back_x(length_px=length_px)
    write_sequence(folder, [window(tex, x, y=40.0) for x in xs])
    return xs
