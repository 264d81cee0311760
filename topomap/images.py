"""Image sequences: listing (natural sort), reading (any depth, colour or grey), video frames, resizing.

Every image enters topomap through :func:`read_image` / :func:`to_gray_u8`, which return a
``(H, W) uint8`` grayscale array whatever the file held (8/16-bit, float, grey, BGR, BGRA), so the
rest of the library never has to think about depth or channels.

Encoded bytes from anywhere (files, map BLOBs, textures, bag messages) pass one gate,
:func:`decode_image`: it reads the size the header *declares* (:func:`probe_image`) and refuses an
image above the pixel limit before a byte is decoded (a decompression bomb of a few hundred KB can
declare 30000 x 30000 pixels), refuses a cut-short file before decoding it, and keeps the codecs'
own warnings off stderr. Files are opened only when they are regular files (a FIFO or a device
would block or never end) and only up to :data:`MAX_IMAGE_BYTES`.

A *source* for :func:`open_sequence` is an image folder, a video file, a text file listing one
image path per line (relative paths are relative to the list file), or one of the sources
registered in :mod:`topomap.sources` (ROS 1 / ROS 2 bags, MCAP).
"""

from __future__ import annotations

import contextlib
import errno
import io
import logging
import os
import re
import stat
import struct
import sys
import tempfile
import threading
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from topomap.errors import DatasetError

if TYPE_CHECKING:
    from topomap.camera import CameraIntrinsics

__all__ = [
    "IMAGE_EXTENSIONS",
    "VIDEO_EXTENSIONS",
    "MAX_IMAGE_PIXELS",
    "MAX_IMAGE_BYTES",
    "MAX_WORKING_SIDE_PX",
    "ImageInfo",
    "probe_image",
    "decode_image",
    "read_file_bytes",
    "display_name",
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

IMAGE_EXTENSIONS = frozenset({".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".pnm", ".webp", ".gif"})
VIDEO_EXTENSIONS = frozenset({".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv"})
LIST_EXTENSIONS = frozenset({".txt", ".lst", ".list"})

#: Largest image decoded by default [pixels]: a 50 MP camera (8160 x 6120) fits; decoding one in
#: colour takes 150 MB. A header declaring more is refused before anything is decoded.
MAX_IMAGE_PIXELS = 50_000_000
#: Largest image file read [bytes]; larger files are refused unread.
MAX_IMAGE_BYTES = 256 << 20
#: Longest side of the working resolution when no ``resize_max_px`` asks for less [px]: a huge first
#: frame must not set a working size that every later frame is enlarged to.
MAX_WORKING_SIDE_PX = 4096
#: Largest list file read (one path a line) [bytes].
MAX_LIST_BYTES = 64 << 20


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
    try:
        entries = [p for p in folder.iterdir() if not p.name.startswith(".")]
    except OSError as e:
        raise DatasetError(f"cannot list folder {folder}: {e.strerror or e}") from None
    if not entries:
        raise DatasetError(f"folder {folder} is empty; put the sequence's images in it")
    # Entries named like images that are not regular files (a folder "x.jpg", a FIFO, a device, a
    # broken or looping link) are kept: reading them fails with the reason, so the build counts them.
    images = [p for p in entries if p.suffix.lower() in IMAGE_EXTENSIONS]
    if not images:
        exts = ", ".join(sorted(e.lstrip(".") for e in IMAGE_EXTENSIONS))
        raise DatasetError(f"folder {folder} holds no images (looked for {exts})")
    return sorted(images, key=lambda p: natural_key(p.name))


def display_name(name: str) -> str:
    """A file name safe to print and to store as UTF-8 text: bytes that were not UTF-8 (a Latin-1
    ``caf\xe9.jpg``, which Python holds as a lone surrogate) become a ``\\xe9`` escape."""
    try:
        name.encode("utf-8")
        return name
    except UnicodeEncodeError:
        return name.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


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


def read_file_bytes(path: str | Path, *, max_bytes: int = MAX_IMAGE_BYTES, what: str = "image") -> bytes:
    """The bytes of a *regular* file of at most ``max_bytes``, or a one-line :class:`DatasetError`.

    The file is opened without blocking and checked with ``fstat`` before a byte is read: a FIFO
    would block forever and ``/dev/zero`` never ends; folders, devices and link loops get their reason.
    """
    path = Path(path)
    name = display_name(path.name)
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_BINARY", 0))
    except FileNotFoundError:
        if path.is_symlink():
            raise DatasetError(f"{what} {name} is a broken symbolic link") from None
        raise DatasetError(f"{what} {display_name(str(path))} does not exist") from None
    except IsADirectoryError:
        raise DatasetError(f"{what} {name} is a folder, not a file") from None
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise DatasetError(f"{what} {name} is a symbolic link loop") from None
        raise DatasetError(f"cannot read {what} {name}: {e.strerror or e}") from None
    st = os.fstat(fd)
    if not stat.S_ISREG(st.st_mode):
        os.close(fd)
        if stat.S_ISDIR(st.st_mode):
            raise DatasetError(f"{what} {name} is a folder, not a file")
        kind = "a FIFO" if stat.S_ISFIFO(st.st_mode) else "a device" if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode) else "a socket" if stat.S_ISSOCK(st.st_mode) else "not a regular file"
        raise DatasetError(f"{what} {name} is {kind}, not a regular file")
    with os.fdopen(fd, "rb") as fh:
        if st.st_size > max_bytes:
            raise DatasetError(f"{what} {name} is {st.st_size / 2**20:.0f} MB, more than the {max_bytes / 2**20:.0f} MB topomap reads")
        try:
            data = fh.read(max_bytes + 1)
        except OSError as e:
            raise DatasetError(f"cannot read {what} {name}: {e.strerror or e}") from None
    if len(data) > max_bytes:  # grew while being read
        raise DatasetError(f"{what} {name} is larger than the {max_bytes / 2**20:.0f} MB topomap reads")
    return data


def read_image(path: str | Path, *, max_pixels: int = MAX_IMAGE_PIXELS) -> np.ndarray:
    """Read an image file as ``(H, W) uint8`` grayscale; EXIF orientation is applied.

    Raises :class:`DatasetError` (one line) when the file is missing, empty, truncated, not an
    image, not a regular file, or declares more than ``max_pixels`` pixels.
    """
    path = Path(path)
    data = read_file_bytes(path)
    if not data:
        raise DatasetError(f"image {display_name(path.name)} is an empty file")
    return decode_image(data, max_pixels=max_pixels, what=f"image {display_name(path.name)}")


@dataclass(frozen=True)
class ImageInfo:
    """What an encoded image's header declares: ``format`` (``PNG``, ``JPEG``, ...), ``width`` and
    ``height`` [px] and ``channels`` (None when the header does not say)."""

    format: str
    width: int
    height: int
    channels: int | None = None

    @property
    def pixels(self) -> int:
        return self.width * self.height


#: Formats the gate lets through to a decoder (Pillow names).
DECODABLE_FORMATS = ("PNG", "JPEG", "BMP", "TIFF", "WEBP", "PPM", "GIF")
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def probe_image(data: bytes, what: str = "image") -> ImageInfo:
    """Format and declared size of encoded image bytes, read from the header only (nothing decoded).

    PNG and JPEG headers are parsed here (Pillow's ``open`` costs 50 us, 40% of decoding a map
    thumbnail, and a map holds 100k of them); other formats through Pillow's lazy ``open``.
    """
    if len(data) == 0:
        raise DatasetError(f"{what} is empty")
    head = bytes(data[:8])
    if head == _PNG_MAGIC:
        if len(data) < 33 or bytes(data[12:16]) != b"IHDR":
            raise DatasetError(f"{what} is not a valid PNG (no header)")
        w, h = struct.unpack(">II", bytes(data[16:24]))
        channels = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}.get(data[25])
        return ImageInfo("PNG", w, h, channels)
    if head[:2] == b"\xff\xd8":
        return _probe_jpeg(data, what)
    if head[:1] == b"P" and head[1:2] in (b"1", b"2", b"3", b"4", b"5", b"6"):
        return _probe_pnm(data, what)
    from PIL import Image  # pillow is a dependency; imported here as only rare formats need it

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with Image.open(io.BytesIO(data), formats=DECODABLE_FORMATS) as im:
                w, h = im.size
                fmt = str(im.format)
                channels = len(im.getbands())
    except Image.DecompressionBombError:  # Pillow refuses to even open it
        raise DatasetError(f"{what} declares more pixels than the {MAX_IMAGE_PIXELS / 1e6:.0f} Mpx topomap decodes "
                           "(a decompression bomb or a far too large image); shrink it first") from None
    except Exception:  # a parser of untrusted bytes: any failure means "not an image we read"
        raise DatasetError(f"{what} is not a readable image (unknown format, corrupt or truncated)") from None
    return ImageInfo(fmt, int(w), int(h), channels)


_PNM_TOKEN = re.compile(rb"(?:\s|#[^\n]*\n)*(\d+)")


def _probe_pnm(buf: bytes, what: str) -> ImageInfo:
    """Width and height from a PBM/PGM/PPM header (``P5 640 480 255``, comments allowed)."""
    pos, vals = 2, []
    for _ in range(2):
        m = _PNM_TOKEN.match(buf, pos, min(len(buf), pos + 4096))
        if m is None:
            raise DatasetError(f"{what} is not a valid PNM image (no size in its header)")
        vals.append(int(m.group(1)))
        pos = m.end()
    return ImageInfo("PPM", vals[0], vals[1], 3 if buf[1:2] in (b"3", b"6") else 1)


def _probe_jpeg(buf: bytes, what: str) -> ImageInfo:
    """Walk the JPEG header segments to the frame header (SOFn) and read its size."""
    i = 2
    while i + 4 <= len(buf):
        if buf[i] != 0xFF:
            break
        marker = buf[i + 1]
        if marker == 0xFF:
            i += 1
            continue
        if marker == 0x01 or 0xD0 <= marker <= 0xD8:
            i += 2
            continue
        if marker in (0xDA, 0xD9):
            break  # scan or end before any frame header
        seg = int.from_bytes(buf[i + 2 : i + 4], "big")
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            if i + 10 > len(buf):
                break
            h, w = struct.unpack(">HH", buf[i + 5 : i + 9])
            return ImageInfo("JPEG", w, h, buf[i + 9])
        i += 2 + seg
    raise DatasetError(f"{what} is not a valid JPEG (no frame header)")


_STDERR_GUARD = threading.Lock()
_scratch: tuple[int, int] | None = None  # (pid, fd) of the file libjpeg's warnings are caught in


@contextlib.contextmanager
def _quiet_stderr():
    """libjpeg prints its warnings ("Corrupt JPEG data: ...") to the process's stderr itself, not
    through OpenCV's logger. While OpenCV decodes a JPEG (one thread at a time), file descriptor 2
    points at a scratch file; what was said is logged at debug level."""
    global _scratch
    with _STDERR_GUARD:
        try:
            if _scratch is None or _scratch[0] != os.getpid():
                _scratch = (os.getpid(), _tmpfile_fd())
            fd = _scratch[1]
            os.ftruncate(fd, 0)
            os.lseek(fd, 0, os.SEEK_SET)
            sys.stderr.flush()
            saved = os.dup(2)
        except OSError:  # no stderr, or no scratch file: decode unguarded
            yield
            return
        os.dup2(fd, 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            try:
                os.lseek(fd, 0, os.SEEK_SET)
                said = os.read(fd, 4096)
            except OSError:
                said = b""
            if said.strip():
                log.debug("decoder said: %s", said.decode(errors="replace").strip().replace("\n", "; "))


def _tmpfile_fd() -> int:
    """A descriptor of an anonymous temporary file (already unlinked: nothing is left behind)."""
    fh = tempfile.TemporaryFile()
    fd = os.dup(fh.fileno())
    fh.close()
    return fd


def _quiet_ffmpeg() -> None:
    """OpenCV's FFmpeg backend prints FFmpeg's own messages ("moov atom not found") to stderr at the
    level this variable sets, read when the first video is opened; a user's own setting is kept."""
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET


@contextlib.contextmanager
def _quiet_opencv():
    """OpenCV's codec warnings ("PNG input buffer is incomplete", ...) go to stderr directly; the
    library never prints, and the error it raises says the same in one line."""
    logging_mod = getattr(getattr(cv2, "utils", None), "logging", None)
    if logging_mod is None:  # pragma: no cover - very old OpenCV
        yield
        return
    previous = logging_mod.getLogLevel()
    logging_mod.setLogLevel(logging_mod.LOG_LEVEL_SILENT)
    try:
        yield
    finally:
        logging_mod.setLogLevel(previous)


def decode_image(
    data: bytes | bytearray | memoryview | np.ndarray,
    *,
    max_pixels: int = MAX_IMAGE_PIXELS,
    max_size: tuple[int, int] | None = None,
    formats: tuple[str, ...] | None = None,
    color: bool = False,
    what: str = "image",
) -> np.ndarray:
    """Encoded image bytes -> ``(H, W) uint8`` grayscale (``color=True``: ``(H, W, 3) uint8`` BGR).

    The one gate every encoded image passes: the declared size is checked against ``max_pixels``
    and ``max_size = (w, h)`` (each side at most) before decoding, ``formats`` (Pillow names, e.g.
    ``("PNG", "JPEG")``) restricts what is accepted, a cut-short PNG or JPEG is refused before the
    decoder fills it with grey, and codec warnings stay off stderr. Any failure is one
    :class:`DatasetError` line naming ``what``.
    """
    if isinstance(data, np.ndarray):
        data = np.ascontiguousarray(data).reshape(-1).view(np.uint8).tobytes()
    elif not isinstance(data, bytes):
        data = bytes(data)
    info = probe_image(data, what)
    buf = np.frombuffer(data, np.uint8)
    if formats is not None and info.format not in formats:
        raise DatasetError(f"{what} is {info.format}, expected {' or '.join(formats)}")
    if info.width < 1 or info.height < 1:
        raise DatasetError(f"{what} declares an empty size ({info.width}x{info.height} px)")
    if max_size is not None and (info.width > max_size[0] or info.height > max_size[1]):
        raise DatasetError(f"{what} declares {info.width}x{info.height} pixels, more than {max_size[0]}x{max_size[1]}")
    if info.pixels > max_pixels:
        limit = f"{max_pixels / 1e6:.0f} Mpx" if max_pixels >= 1e6 else f"{max_pixels} pixels"
        raise DatasetError(
            f"{what} declares {info.width}x{info.height} pixels, more than the {limit} topomap "
            "decodes (a decompression bomb or a far too large image); shrink it first"
        )
    if _looks_truncated(buf):
        raise DatasetError(f"{what} is truncated")
    try:
        with _quiet_opencv(), (_quiet_stderr() if info.format == "JPEG" else contextlib.nullcontext()):
            img = cv2.imdecode(buf, cv2.IMREAD_COLOR if color else cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR)
    except cv2.error:
        img = None
    if img is None or img.size == 0:
        raise DatasetError(f"{what} is not a readable image (corrupt, truncated or not an image)")
    if img.shape[0] * img.shape[1] > info.pixels:  # the decoder must not produce more than declared
        raise DatasetError(f"{what} decodes to more pixels than its header declares")
    if color:
        return img if img.ndim == 3 else cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    return to_gray_u8(img)


def _looks_truncated(data: np.ndarray, path: Path | None = None) -> bool:
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
    local features no room, but a too large enlargement only invents texture. The longest side never
    exceeds :data:`MAX_WORKING_SIDE_PX`."""
    longest = max(width, height)
    scale = 1.0
    if resize_max_px and longest > resize_max_px:
        scale = resize_max_px / longest
    elif upscale_min_px and longest < upscale_min_px:
        scale = min(upscale_min_px / longest, max_upscale)
    scale = min(scale, MAX_WORKING_SIDE_PX / longest)
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

    #: intrinsics the source itself carries (a bag's CameraInfo), else None
    camera: CameraIntrinsics | None = None

    def __init__(self, source: str | Path, every: int = 1):
        self.source = Path(source)
        if every < 1:
            raise DatasetError(f"--every must be at least 1, got {every}")
        self.every = int(every)
        self._paths: list[Path] | None = None
        self._video_frames = 0
        src = self.source
        if not src.exists():
            if src.is_symlink():
                raise DatasetError(f"{display_name(str(src))} is a broken symbolic link or a link loop")
            raise DatasetError(f"{display_name(str(src))} does not exist; give an image folder, a video or a list file")
        if not src.is_dir() and not src.is_file():
            raise DatasetError(f"{display_name(str(src))} is not a regular file or folder (a FIFO or a device?); "
                               "give an image folder, a video or a list file")
        if src.is_dir():
            self.kind = "folder"
            self._paths = list_images(src)[:: self.every]
        elif src.suffix.lower() in VIDEO_EXTENSIONS:
            self.kind = "video"
            _quiet_ffmpeg()
            with _quiet_opencv():
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
        data = read_file_bytes(path, max_bytes=MAX_LIST_BYTES, what="list file")
        try:
            lines = data.decode("utf-8").splitlines()
        except UnicodeDecodeError:
            lines = data.decode("utf-8", "surrogateescape").splitlines()  # Latin-1 paths still open
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
        return [display_name(p.name) for p in self._paths] if self._paths is not None else None

    def __iter__(self) -> Iterator[Frame]:
        if self._paths is not None:
            for i, p in enumerate(self._paths):
                name = display_name(p.name)
                try:
                    yield Frame(i, name, read_image(p), path=str(p))
                except DatasetError as e:
                    yield Frame(i, name, None, str(e), path=str(p))
            return
        with _quiet_opencv():
            cap = cv2.VideoCapture(str(self.source))
        try:
            raw = kept = 0
            while True:
                with _quiet_opencv():
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


def open_sequence(source: str | Path, every: int = 1, topic: str | None = None) -> ImageSequence:
    """An :class:`ImageSequence` over a folder, a video, a list file, a single image or a ROS bag
    (``topic``: its image topic, see :mod:`topomap.sources`)."""
    from topomap.sources import open_source  # the registered sources (bags: rosbags loads lazily)

    seq = open_source(source, every, topic)
    if seq is not None:
        return seq
    if topic is not None:
        raise DatasetError(f"--topic is for ROS bags; {Path(source).name} is not a bag (.bag, .mcap, .db3 or a rosbag2 folder)")
    return ImageSequence(source, every)
