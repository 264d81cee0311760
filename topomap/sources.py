"""Image sources beyond files: ROS 1 bags, ROS 2 bags (sqlite3 or MCAP storage) and bare MCAP files.

:func:`topomap.images.open_sequence` asks :func:`open_source` first; a path that no registered source
claims falls through to the file sources of :mod:`topomap.images` (folder, video, list, image). Every
source hands out one :class:`~topomap.images.ImageSequence`, so the rest of topomap cannot tell a bag
from a folder: frames come as ``(H, W) uint8`` grayscale, in recording order.

ROS bags are read with the pure-Python ``rosbags`` library (the optional extra
``appearance-topomap[bags]``), imported only when a bag is opened.

* Topics of type ``sensor_msgs/Image`` (encodings in :data:`RAW_ENCODINGS`: mono8/16, rgb/bgr/rgba/bgra
  at 8 and 16 bits, ``8UC1..4``, ``16UC1``, ``32FC1``, Bayer, YUV 4:2:2, NV12/NV21; row padding
  ``step`` and ``is_bigendian`` honoured) and ``sensor_msgs/CompressedImage`` (JPEG, PNG, anything
  OpenCV decodes, ``compressedDepth`` PNG).
* Frame names are the header stamps ``"<sec>.<nanosec>"`` (the bag's record time when a header
  stamp is zero); the frame path is ``BAG#TOPIC@<record time ns>``.
* Intrinsics come from the ``sensor_msgs/CameraInfo`` topic of the image topic's namespace
  (``/cam/image_raw`` -> ``/cam/camera_info``; the bag's only CameraInfo topic otherwise), with
  binning and region of interest applied; an uncalibrated one (K all zero) is ignored.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from topomap.camera import CameraIntrinsics
from topomap.errors import DatasetError, MissingExtraError
from topomap.images import IMAGE_EXTENSIONS, MAX_IMAGE_PIXELS, Frame, ImageSequence, _looks_truncated, probe_image, to_gray_u8

__all__ = [
    "SOURCES",
    "BAG_SUFFIXES",
    "RAW_ENCODINGS",
    "MAX_IMAGE_PIXELS",
    "ImageTopic",
    "BagSequence",
    "open_source",
    "decode_compressed",
    "decode_raw",
    "camera_from_info",
]

log = logging.getLogger(__name__)

#: File suffixes read as bags: ROS 1 ``.bag``, a ROS 2 storage file ``.db3`` / ``.mcap``.
BAG_SUFFIXES = frozenset({".bag", ".db3", ".mcap"})

IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
_IMAGE_TYPES = (IMAGE_TYPE, COMPRESSED_TYPE)


@dataclass(frozen=True)
class _Encoding:
    """How a raw encoding lies in memory: element type, channels, and the OpenCV conversion to
    grey or BGR (None: already grey/BGR); ``rows``: stored rows per image row (NV12: 1.5)."""

    dtype: str
    channels: int
    convert: int | None = None
    rows: float = 1.0


#: ``sensor_msgs/Image`` encodings topomap reads (names as in ROS ``sensor_msgs/image_encodings.h``).
#: ROS's bayer_rggb is OpenCV's BayerBG (OpenCV names the pattern from the second row and column).
RAW_ENCODINGS: dict[str, _Encoding] = {
    "mono8": _Encoding("u1", 1), "8UC1": _Encoding("u1", 1),
    "mono16": _Encoding("u2", 1), "16UC1": _Encoding("u2", 1),
    "bgr8": _Encoding("u1", 3), "8UC3": _Encoding("u1", 3),
    "rgb8": _Encoding("u1", 3, cv2.COLOR_RGB2BGR),
    "bgra8": _Encoding("u1", 4, cv2.COLOR_BGRA2BGR), "8UC4": _Encoding("u1", 4, cv2.COLOR_BGRA2BGR),
    "rgba8": _Encoding("u1", 4, cv2.COLOR_RGBA2BGR),
    "bgr16": _Encoding("u2", 3), "16UC3": _Encoding("u2", 3),
    "rgb16": _Encoding("u2", 3, cv2.COLOR_RGB2BGR),
    "bgra16": _Encoding("u2", 4, cv2.COLOR_BGRA2BGR), "rgba16": _Encoding("u2", 4, cv2.COLOR_RGBA2BGR),
    "32FC1": _Encoding("f4", 1), "64FC1": _Encoding("f8", 1),
    "bayer_rggb8": _Encoding("u1", 1, cv2.COLOR_BayerBG2GRAY), "bayer_bggr8": _Encoding("u1", 1, cv2.COLOR_BayerRG2GRAY),
    "bayer_gbrg8": _Encoding("u1", 1, cv2.COLOR_BayerGR2GRAY), "bayer_grbg8": _Encoding("u1", 1, cv2.COLOR_BayerGB2GRAY),
    "bayer_rggb16": _Encoding("u2", 1, cv2.COLOR_BayerBG2GRAY), "bayer_bggr16": _Encoding("u2", 1, cv2.COLOR_BayerRG2GRAY),
    "bayer_gbrg16": _Encoding("u2", 1, cv2.COLOR_BayerGR2GRAY), "bayer_grbg16": _Encoding("u2", 1, cv2.COLOR_BayerGB2GRAY),
    "uyvy": _Encoding("u1", 2, cv2.COLOR_YUV2GRAY_UYVY), "yuv422": _Encoding("u1", 2, cv2.COLOR_YUV2GRAY_UYVY),
    "yuyv": _Encoding("u1", 2, cv2.COLOR_YUV2GRAY_YUY2), "yuv422_yuy2": _Encoding("u1", 2, cv2.COLOR_YUV2GRAY_YUY2),
    "nv12": _Encoding("u1", 1, None, 1.5), "nv21": _Encoding("u1", 1, None, 1.5),  # the Y plane comes first
}


# ----------------------------------------------------------------------------- decoding
def _check_size(width: int, height: int, what: str) -> None:
    if width <= 0 or height <= 0:
        raise DatasetError(f"{what} is {width}x{height} pixels")
    if width * height > MAX_IMAGE_PIXELS:
        raise DatasetError(f"{what} is {width}x{height} pixels, more than the {MAX_IMAGE_PIXELS // 1_000_000} MP topomap reads")


def _encoding(name: str) -> _Encoding:
    enc = RAW_ENCODINGS.get(name)
    if enc is None:
        raise DatasetError(
            f"image encoding {name!r} is not supported; topomap reads {', '.join(sorted(RAW_ENCODINGS, key=str.lower))}"
        )
    return enc


def decode_raw(encoding: str, width: int, height: int, step: int, is_bigendian: bool, data) -> np.ndarray:
    """A ``sensor_msgs/Image`` payload -> ``(H, W)`` or ``(H, W, 3)`` BGR array of its own depth.

    ``step`` is the stored row length [bytes] (rows may be padded); multi-byte elements are read in
    the byte order ``is_bigendian`` says. Raises :class:`DatasetError` for an unknown encoding or a
    payload that does not hold ``height`` rows of ``step`` bytes.
    """
    enc = _encoding(encoding)
    width, height, step = int(width), int(height), int(step)
    _check_size(width, height, f"a {encoding} image")
    dtype = np.dtype(enc.dtype).newbyteorder(">" if is_bigendian else "<")
    row_bytes = width * enc.channels * dtype.itemsize
    rows = int(math.ceil(height * enc.rows))
    if step < row_bytes:
        raise DatasetError(f"{encoding} image row step {step} B is shorter than its {width} pixels ({row_bytes} B)")
    buf = np.frombuffer(memoryview(data), np.uint8)
    need = step * (rows - 1) + row_bytes  # the last row need not be padded
    if buf.size < need:
        raise DatasetError(f"{encoding} image {width}x{height} holds {buf.size} B of the {need} B its rows need (truncated)")
    if buf.size < step * rows:
        buf = np.concatenate([buf[:need], np.zeros(step * rows - need, np.uint8)])
    img = buf[: step * rows].reshape(rows, step)[:, :row_bytes]
    img = np.ascontiguousarray(img).view(dtype).reshape(rows, width, enc.channels) if enc.channels > 1 else \
        np.ascontiguousarray(img).view(dtype).reshape(rows, width)
    if not dtype.isnative:
        img = img.astype(dtype.newbyteorder("="))
    if enc.rows != 1.0:
        return img[:height]
    if enc.convert is not None:
        img = cv2.cvtColor(img, enc.convert)
    return img


def decode_compressed(data, fmt: str = "") -> np.ndarray:
    """A ``sensor_msgs/CompressedImage`` payload -> image array as OpenCV decodes it (grey, BGR or
    16-bit). ``fmt`` is the message's ``format`` (``jpeg``, ``png``, ``bgr8; jpeg compressed bgr8``,
    ``16UC1; compressedDepth png``...). The header's size is checked before anything is decoded.

    This is the one place compressed payloads are decoded.
    """
    buf = bytes(data)
    if "compresseddepth" in fmt.lower():
        start = buf.find(b"\x89PNG")  # compressedDepth puts a 12-byte depth-quantisation header first
        buf = buf[start:] if start >= 0 else buf
    if not buf:
        raise DatasetError("compressed image message holds no data")
    what = f"compressed image ({fmt or 'no format given'})"
    info = probe_image(buf, what)  # the image gate's header probe: the declared size, nothing decoded
    _check_size(info.width, info.height, what)
    arr = np.frombuffer(buf, np.uint8)
    if _looks_truncated(arr, Path("payload")):  # JPEG decoders fill a cut payload with grey and succeed
        raise DatasetError(f"compressed image ({fmt or 'no format given'}) is truncated")
    img = cv2.imdecode(arr, cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR)
    if img is None or img.size == 0:
        raise DatasetError(f"compressed image ({fmt or 'no format given'}) is corrupt or truncated")
    return img


def camera_from_info(msg, source: str = "camera_info") -> CameraIntrinsics | None:
    """``sensor_msgs/CameraInfo`` (ROS 1 ``K, D`` or ROS 2 ``k, d``) -> intrinsics of the images it
    describes (binning and region of interest applied), or None when uncalibrated (K zero)."""
    K = np.asarray(msg.k if hasattr(msg, "k") else msg.K, float).reshape(3, 3)
    if not (np.isfinite(K).all() and K[0, 0] > 0 and K[1, 1] > 0):
        log.warning("%s holds no calibration (K is zero); using --camera or the default camera", source)
        return None
    D = [float(x) for x in (msg.d if hasattr(msg, "d") else msg.D)]
    model = str(msg.distortion_model or "")
    if model in ("plumb_bob", "rational_polynomial", ""):
        if any(abs(x) > 0 for x in D[5:]):
            log.warning("%s: %s coefficients beyond k3 are ignored", source, model)
        dist = D[:5]
    else:
        log.warning("%s: distortion model %r is not supported; distortion ignored", source, model)
        dist = []
    bx, by = max(1, int(msg.binning_x)), max(1, int(msg.binning_y))
    roi = msg.roi
    x0, y0 = (int(roi.x_offset), int(roi.y_offset)) if roi.width and roi.height else (0, 0)
    w = int(roi.width) if roi.width and roi.height else int(msg.width)
    h = int(roi.height) if roi.width and roi.height else int(msg.height)
    cam = CameraIntrinsics(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]) - x0, float(K[1, 2]) - y0, w, h,
                           float(K[0, 1]), tuple(dist) + (0.0,) * (5 - len(dist)), source=source)
    return cam.scaled(1.0 / bx, 1.0 / by, w // bx, h // by) if (bx, by) != (1, 1) else cam


# ----------------------------------------------------------------------------- bags
def _rosbags():
    """The rosbags modules, or the one-line error that says how to install them."""
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise MissingExtraError(
            "reading ROS bags needs the rosbags library: pip install 'appearance-topomap[bags]'"
        ) from None
    return AnyReader, get_typestore(Stores.LATEST)


def _is_bag(path: Path) -> bool:
    """A bag file, a rosbag2 folder, or a folder of storage files and no images (metadata lost)."""
    if not path.is_dir():
        return path.suffix.lower() in BAG_SUFFIXES
    if (path / "metadata.yaml").is_file():
        return True
    suffixes = {p.suffix.lower() for p in path.iterdir()}
    return bool(suffixes & {".db3", ".mcap"}) and not suffixes & IMAGE_EXTENSIONS


@dataclass(frozen=True)
class ImageTopic:
    """An image topic of a bag: ``name``, message ``type`` (``sensor_msgs/msg/Image`` or
    ``.../CompressedImage``) and its number of ``messages``."""

    name: str
    type: str
    messages: int

    def __str__(self) -> str:
        return f"{self.name} ({self.type.replace('/msg/', '/')}, {self.messages} messages)"


def _stamp_ns(msg, record_ns: int) -> int:
    st = msg.header.stamp
    ns = int(st.sec) * 1_000_000_000 + int(st.nanosec)
    return ns if ns > 0 else int(record_ns)


def _stamp_name(ns: int) -> str:
    return f"{ns // 1_000_000_000}.{ns % 1_000_000_000:09d}"


class BagSequence(ImageSequence):
    """The frames of one image topic of a ROS 1 bag, a ROS 2 bag folder (sqlite3 or MCAP storage)
    or a bare ``.mcap`` / ``.db3`` storage file. ``topic`` may be omitted when the bag has one image
    topic. ``camera``: intrinsics from the topic's CameraInfo, or None.

    Iterating opens the bag anew each time; frames whose message cannot be decoded come with their
    ``error`` (like unreadable files in a folder). An unsupported encoding fails at opening.
    """

    kind = "bag"

    def __init__(self, source: str | Path, every: int = 1, topic: str | None = None):
        self.source = Path(source)
        if every < 1:
            raise DatasetError(f"--every must be at least 1, got {every}")
        self.every = int(every)
        self._names: list[str] | None = None
        if not self.source.exists():
            raise DatasetError(f"{self.source} does not exist; give a ROS bag (.bag, .mcap, .db3 or a rosbag2 folder)")
        self._AnyReader, self._typestore = _rosbags()
        if self.source.is_dir() and not (self.source / "metadata.yaml").is_file():
            # a rosbag2 folder that lost its metadata: its one storage file is readable by itself
            files = sorted(p for p in self.source.iterdir() if p.suffix in (".db3", ".mcap"))
            if len(files) != 1:
                raise DatasetError(f"{self.source} has no metadata.yaml and {len(files)} storage files; give one of them")
            self.source = files[0]
        with self._open() as reader:
            self.topics = self._image_topics(reader)
            self.topic = self._choose(topic, reader)
            conns = [c for c in reader.connections if c.topic == self.topic]
            self._count = sum(int(c.msgcount) for c in conns)
            self._check_first(reader, conns)
            self.camera = self._camera(reader)

    # -- opening and inspecting
    @contextmanager
    def _open(self):
        try:
            reader = self._AnyReader([self.source], default_typestore=self._typestore)
            reader.open()
        except Exception as e:  # rosbags raises many kinds on corrupt input; all mean "not a readable bag"
            hint = "; a ROS 1 bag cut short needs `rosbag reindex`" if self.source.suffix == ".bag" and "index" in str(e).lower() else ""
            raise DatasetError(f"{self.source.name} is not a readable ROS bag ({_first_line(e)}){hint}") from None
        try:
            yield reader
        finally:
            with suppress(Exception):  # closing the reader of a damaged file may fail again: the first error counts
                reader.close()

    def _image_topics(self, reader) -> list[ImageTopic]:
        counts: dict[tuple[str, str], int] = {}
        for c in reader.connections:
            if c.msgtype in _IMAGE_TYPES:
                counts[(c.topic, c.msgtype)] = counts.get((c.topic, c.msgtype), 0) + int(c.msgcount)
        return [ImageTopic(t, ty, n) for (t, ty), n in sorted(counts.items())]

    def _choose(self, topic: str | None, reader) -> str:
        listed = "; ".join(str(t) for t in self.topics)
        if not self.topics:
            have = sorted({f"{c.topic} ({c.msgtype.replace('/msg/', '/')})" for c in reader.connections})
            raise DatasetError(
                f"{self.source.name} has no image topic (sensor_msgs/Image or CompressedImage); it has: "
                f"{', '.join(have) if have else 'no topics'}"
            )
        if topic is None:
            if len(self.topics) == 1:
                log.info("reading image topic %s", self.topics[0])
                return self.topics[0].name
            raise DatasetError(f"{self.source.name} has {len(self.topics)} image topics: {listed}; choose one with --topic")
        if topic not in {t.name for t in self.topics}:
            raise DatasetError(f"{self.source.name} has no image topic {topic!r}; its image topics: {listed}")
        return topic

    def _messages(self, reader, conns) -> Iterator[tuple[int, int, object, str]]:
        """(record time ns, message index, message or None, error) of the topic, in record order."""
        try:
            for i, (conn, t, raw) in enumerate(reader.messages(connections=conns)):
                try:
                    msg = reader.deserialize(raw, conn.msgtype)
                except Exception as e:  # a damaged message: the frame is skipped with the reason
                    yield int(t), i, None, f"message cannot be decoded ({_first_line(e)})"
                    continue
                yield int(t), i, msg, ""
        except DatasetError:
            raise
        except Exception as e:
            raise DatasetError(f"{self.source.name} is damaged: reading {self.topic} failed ({_first_line(e)})") from None

    def _check_first(self, reader, conns) -> None:
        for _, _, msg, _ in self._messages(reader, conns):
            if msg is not None and hasattr(msg, "encoding"):
                _encoding(msg.encoding)  # an unsupported encoding fails now, not frame by frame
            return

    def _camera(self, reader) -> CameraIntrinsics | None:
        infos = sorted({c.topic for c in reader.connections if c.msgtype == CAMERA_INFO_TYPE})
        if not infos:
            return None
        parts = self.topic.strip("/").split("/")
        chosen = None
        for k in range(len(parts) - 1, -1, -1):  # the image topic's namespace, then its parents
            want = "/" + "/".join(parts[:k] + ["camera_info"])
            if want in infos:
                chosen = want
                break
        if chosen is None:
            if len(infos) > 1:
                log.warning("%s: none of the CameraInfo topics %s is in %s's namespace; give --camera",
                            self.source.name, ", ".join(infos), self.topic)
                return None
            chosen = infos[0]
        conns = [c for c in reader.connections if c.topic == chosen]
        for _, _, msg, _ in self._messages(reader, conns):
            if msg is not None:
                return camera_from_info(msg, f"{self.source.name}:{chosen}")
        return None

    # -- the sequence
    @property
    def paths(self) -> None:
        """A bag's frames are messages, not files: they only exist by decoding (read in order)."""
        return None

    def __len__(self) -> int:
        return (self._count + self.every - 1) // self.every

    @property
    def names(self) -> list[str]:
        """Frame names in order (one pass over the topic's messages, then cached)."""
        if self._names is None:
            self._names = [name for name, *_ in self._frames(decode=False)]
        return list(self._names)

    def _frames(self, decode: bool = True) -> Iterator[tuple[str, np.ndarray | None, str, str]]:
        """(name, image, error, path) of every kept message."""
        seen: dict[str, int] = {}
        with self._open() as reader:
            conns = [c for c in reader.connections if c.topic == self.topic]
            for t, i, msg, error in self._messages(reader, conns):
                if i % self.every:
                    continue
                name = _stamp_name(_stamp_ns(msg, t) if msg is not None else t)
                dup = seen.get(name, 0)
                seen[name] = dup + 1
                name = name if dup == 0 else f"{name}-{dup}"  # repeated stamps keep unique names
                path = f"{self.source}#{self.topic}@{t}"
                image = None
                if msg is not None and decode:
                    try:
                        image = to_gray_u8(_decode_message(msg))
                    except DatasetError as e:
                        error = str(e)
                yield name, image, error, path

    def __iter__(self) -> Iterator[Frame]:
        for k, (name, image, error, path) in enumerate(self._frames()):
            yield Frame(k, name, image, error or None, path=path)


def _decode_message(msg) -> np.ndarray:
    if hasattr(msg, "encoding"):
        return decode_raw(msg.encoding, msg.width, msg.height, msg.step, bool(msg.is_bigendian), msg.data)
    return decode_compressed(msg.data, str(msg.format))


def _first_line(e: BaseException) -> str:
    text = str(e).strip() or type(e).__name__
    return text.splitlines()[0][:200]


# ----------------------------------------------------------------------------- registry
#: Registered sources: name -> (claims(path) -> bool, open(path, every, topic) -> ImageSequence).
SOURCES: dict[str, tuple[Callable[[Path], bool], Callable[..., ImageSequence]]] = {
    "rosbag": (_is_bag, BagSequence),
}


def open_source(source: str | Path, every: int = 1, topic: str | None = None) -> ImageSequence | None:
    """The sequence of the first registered source that claims ``source``; None when none does
    (then it is a file source of :mod:`topomap.images`)."""
    path = Path(source)
    for claims, opener in SOURCES.values():
        if path.exists() and claims(path):
            return opener(path, every, topic)
    return None
