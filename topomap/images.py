"""Image sequences: listing (natural sort), reading (any depth, colour or grey), video frames, resizing.

Every image enters topomap through :func:`read_image` / :func:`to_gray_u8`, which return a
``(H, W) uint8`` grayscale array whatever the file held (8/16-bit, float, grey, BGR, BGRA), so the
rest of the library never has to think about depth or channels.

A *source* for :func:`open_sequence` is an image folder, a video file, or a text file listing one
image path per line (relative paths are relative to the list file).
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from topomap.errors import DatasetError

__all__ = [
    "IMAGE_EXTENSIONS",
    "VIDEO_EXTENSIONS",
    "Frame",
    "ImageSequence",
    "natural_key",
    "list_images",
    "read_image",
    "to_gray_u8",
    "working_size",
    "to_working_resolution",
    "open_sequence",
]

log = logging.getLogger(__name__)

IMAGE_EXTENSIONS = frozenset({".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".pnm", ".webp"})
VIDEO_EXTENSIONS = frozenset({".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv"})
LIST_EXTENSIONS = frozenset({".txt", ".lst", ".list"})


def natural_key(name: str) -> list:
    """Sort key that orders ``img2`` before ``img10`` (digit runs compare as numbers)."""
    return [(0, int(tok), "") if tok.isdigit() else (1, 0, tok.lower()) for tok in re.split(r"(\d+)", name)]


def list_images(folder: str | Path) -> list[Path]:
    """Image files directly inside ``folder``, naturally sorted. Raises if there are none."""
    folder = Path(folder)
    if not folder.exists():
        raise DatasetError(f"{folder} does not exist; give an image folder, a video or a list file")
    if not folder.is_dir():
        raise DatasetError(f"{folder} is not a folder")
    entries = [p for p in folder.iterdir() if p.is_file() and not p.name.startswith(".")]
    if not entries:
        raise DatasetError(f"folder {folder} is empty; put the sequence's images in it")
    images = [p for p in entries if p.suffix.lower() in IMAGE_EXTENSIONS]
    if not images:
        exts = ", ".join(sorted(e.lstrip(".") for e in IMAGE_EXTENSIONS))
        raise DatasetError(f"folder {folder} holds no images (looked for {exts})")
    return sorted(images, key=lambda p: natural_key(p.name))


def to_gray_u8(image: np.ndarray) -> np.ndarray:
    """Any image array -> ``(H, W) uint8`` grayscale.

    uint16 is mapped by its bit depth (a 12-bit sensor in a 16-bit container stays bright), floats
    in [0, 1] are scaled by 255, other floats are min-max normalised; alpha is dropped.
    """
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 3:
        if img.shape[2] == 4:
            img = img[:, :, :3]
        if img.shape[2] != 3:
            raise DatasetError(f"image with {img.shape[2]} channels is not supported")
        if img.dtype not in (np.uint8, np.uint16, np.float32):
            img = img.astype(np.float32)
        img = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_BGR2GRAY)
    if img.ndim != 2:
        raise DatasetError(f"array of shape {img.shape} is not an image")
    if img.dtype == np.uint8:
        return np.ascontiguousarray(img)
    if img.dtype == np.uint16 or img.dtype == np.uint32 or img.dtype == np.int32:
        peak = int(img.max()) if img.size else 0
        bits = max(8, int(np.ceil(np.log2(peak + 1))) if peak > 0 else 8)
        bits = 16 if bits > 12 else bits  # 9..12-bit sensor data keeps its depth, else full 16-bit
        return (img.astype(np.uint32) >> (bits - 8)).clip(0, 255).astype(np.uint8)
    if img.dtype == bool:
        return img.astype(np.uint8) * 255
    f = img.astype(np.float32)
    if not np.isfinite(f).all():
        f = np.nan_to_num(f)
    lo, hi = float(f.min()), float(f.max())
    if lo >= 0.0 and hi <= 1.0:
        return (f * 255.0 + 0.5).astype(np.uint8)
    if hi - lo < 1e-12:
        return np.zeros(f.shape, np.uint8)
    return ((f - lo) * (255.0 / (hi - lo)) + 0.5).astype(np.uint8)


def read_image(path: str | Path) -> np.ndarray:
    """Read an image file as ``(H, W) uint8`` grayscale; EXIF orientation is applied.

    Raises :class:`DatasetError` (one line) when the file is missing, empty, truncated or not an image.
    """
    path = Path(path)
    try:
        data = np.fromfile(str(path), dtype=np.uint8)  # fromfile + imdecode: non-ASCII paths work
    except FileNotFoundError:
        raise DatasetError(f"image {path} does not exist") from None
    except OSError as e:
        raise DatasetError(f"cannot read image {path}: {e.strerror or e}") from None
    if data.size == 0:
        raise DatasetError(f"image {path.name} is an empty file")
    img = cv2.imdecode(data, cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR)
    if img is None or img.size == 0:
        raise DatasetError(f"{path.name} is not a readable image (corrupt, truncated or not an image)")
    if _looks_truncated(data, path):
        raise DatasetError(f"image {path.name} is truncated")
    return to_gray_u8(img)


def _looks_truncated(data: np.ndarray, path: Path) -> bool:
    """JPEG decoders fill a cut file with grey and still succeed: check the end-of-image marker.

    A JPEG is whole when an end-of-image marker follows its first scan: data after it (phone
    "motion photo" videos, maker trailers) is allowed, and an EXIF thumbnail's own marker, which
    lies before the scan, does not count.
    """
    if data[:2].tobytes() == b"\xff\xd8":  # JPEG
        buf = data.tobytes()
        sos = _jpeg_scan_start(buf)
        if sos is None:  # header not walkable: only look at the tail
            return b"\xff\xd9" not in buf[-1024:]
        return buf.find(b"\xff\xd9", sos) < 0  # entropy-coded data never holds FF D9
    if data[:8].tobytes() == b"\x89PNG\r\n\x1a\n":
        return b"IEND" not in data[-32:].tobytes()
    return False


def _jpeg_scan_start(buf: bytes) -> int | None:
    """Offset of a JPEG's first start-of-scan marker, found by walking the header segments (their
    payload may hold marker bytes of its own); ``None`` if the header cannot be walked."""
    i = 2
    while i + 4 <= len(buf):
        if buf[i] != 0xFF:
            return None
        marker = buf[i + 1]
        if marker == 0xFF:  # fill byte before a marker
            i += 1
        elif marker == 0xDA:
            return i
        elif marker == 0x01 or 0xD0 <= marker <= 0xD9:  # markers without a length field
            i += 2
        else:
            i += 2 + int.from_bytes(buf[i + 2 : i + 4], "big")
    return None


def working_size(width: int, height: int, resize_max_px: int | None, upscale_min_px: int,
                 max_upscale: float = 3.0) -> tuple[int, int]:
    """Size ``(w, h)`` images are processed at: longest side shrunk to ``resize_max_px`` if larger,
    or enlarged towards ``upscale_min_px`` (by at most ``max_upscale``) if smaller: tiny cameras leave
    local features no room, but a too large enlargement only invents texture."""
    longest = max(width, height)
    scale = 1.0
    if resize_max_px and longest > resize_max_px:
        scale = resize_max_px / longest
    elif upscale_min_px and longest < upscale_min_px:
        scale = min(upscale_min_px / longest, max_upscale)
    if scale == 1.0:
        return width, height
    return max(1, int(round(width * scale))), max(1, int(round(height * scale)))


def to_working_resolution(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Resize ``(H, W)`` to ``size = (w, h)``: area averaging when shrinking, cubic when enlarging."""
    h, w = image.shape[:2]
    if (w, h) == tuple(size):
        return image
    interp = cv2.INTER_AREA if size[0] * size[1] < w * h else cv2.INTER_CUBIC
    return cv2.resize(image, tuple(int(s) for s in size), interpolation=interp)


@dataclass(frozen=True)
class Frame:
    """One element of an image sequence.

    ``index``: position in the sequence (0-based, counting unreadable frames too);
    ``name``: file name (or ``frame_000123`` for video); ``image``: ``(H, W) uint8`` grayscale or
    ``None`` when unreadable, in which case ``error`` says why.
    """

    index: int
    name: str
    image: np.ndarray | None
    error: str | None = None
    path: str = ""


class ImageSequence:
    """An ordered, lazily-read sequence of frames from a folder, a video or a list file.

    ``len()`` is the number of frames (an estimate for videos); iterating yields :class:`Frame`
    objects, unreadable frames included with their ``error`` so callers can count and report them.
    """

    def __init__(self, source: str | Path, every: int = 1):
        self.source = Path(source)
        if every < 1:
            raise DatasetError(f"--every must be at least 1, got {every}")
        self.every = int(every)
        self._paths: list[Path] | None = None
        self._video_frames = 0
        src = self.source
        if not src.exists():
            raise DatasetError(f"{src} does not exist; give an image folder, a video or a list file")
        if src.is_dir():
            self.kind = "folder"
            self._paths = list_images(src)[:: self.every]
        elif src.suffix.lower() in VIDEO_EXTENSIONS:
            self.kind = "video"
            cap = cv2.VideoCapture(str(src))
            ok = cap.isOpened()
            n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) if ok else 0
            cap.release()
            if not ok:
                raise DatasetError(f"cannot open video {src.name} (unsupported codec or corrupt file)")
            self._video_frames = max(0, (n + self.every - 1) // self.every)
        elif src.suffix.lower() in LIST_EXTENSIONS:
            self.kind = "list"
            self._paths = self._read_list(src)[:: self.every]
        elif src.suffix.lower() in IMAGE_EXTENSIONS:
            self.kind = "image"
            self._paths = [src]
        else:
            raise DatasetError(
                f"{src.name} is neither a folder, an image, a video ({', '.join(sorted(VIDEO_EXTENSIONS))}) "
                "nor a list file (.txt)"
            )

    @staticmethod
    def _read_list(path: Path) -> list[Path]:
        try:
            lines = path.read_text().splitlines()
        except (OSError, UnicodeDecodeError) as e:
            raise DatasetError(f"cannot read list file {path}: {e}") from None
        paths = []
        for line in lines:
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            p = Path(line)
            paths.append(p if p.is_absolute() else path.parent / p)
        if not paths:
            raise DatasetError(f"list file {path} names no images")
        return paths

    def __len__(self) -> int:
        return len(self._paths) if self._paths is not None else self._video_frames

    @property
    def paths(self) -> list[Path] | None:
        """The image files in order (``None`` for videos, whose frames only exist by decoding)."""
        return list(self._paths) if self._paths is not None else None

    @property
    def names(self) -> list[str] | None:
        """File names in order (``None`` for videos, whose length is only known by reading)."""
        return [p.name for p in self._paths] if self._paths is not None else None

    def __iter__(self) -> Iterator[Frame]:
        if self._paths is not None:
            for i, p in enumerate(self._paths):
                try:
                    yield Frame(i, p.name, read_image(p), path=str(p))
                except DatasetError as e:
                    yield Frame(i, p.name, None, str(e), path=str(p))
            return
        cap = cv2.VideoCapture(str(self.source))
        try:
            raw = kept = 0
            while True:
                ok, img = cap.read()
                if not ok:
                    break
                if raw % self.every == 0:
                    name = f"frame_{raw:06d}"
                    yield Frame(kept, name, to_gray_u8(img), path=f"{self.source}#{raw}")
                    kept += 1
                raw += 1
        finally:
            cap.release()


def open_sequence(source: str | Path, every: int = 1) -> ImageSequence:
    """An :class:`ImageSequence` over a folder, a video, a list file or a single image."""
    return ImageSequence(source, every)
