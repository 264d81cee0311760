"""Write ROS 1 / ROS 2 (sqlite3, MCAP) bags of given frames with ``rosbags`` (imported by tests).

Each frame becomes one ``sensor_msgs/Image`` (any encoding, optional row padding and byte order) or
``sensor_msgs/CompressedImage`` message stamped ``T0 + i * 0.1 s``; a ``CameraInfo`` message can go
beside them. The same frames written as files (``<stamp>.png``) give the file-source twin.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

__all__ = ["T0_NS", "STORAGES", "stamp_name", "raw_payload", "write_bag", "write_frames_like_bag"]

#: Header stamp of the first frame [ns]; frames follow every 0.1 s.
T0_NS = 1_700_000_000_000_000_000
STEP_NS = 100_000_000

#: Bag flavours: ROS 1 .bag, ROS 2 folder with sqlite3 storage, ROS 2 folder with MCAP storage.
STORAGES = ("ros1", "sqlite3", "mcap")


def stamp_name(i: int) -> str:
    ns = T0_NS + i * STEP_NS
    return f"{ns // 1_000_000_000}.{ns % 1_000_000_000:09d}"


def raw_payload(image: np.ndarray, encoding: str, pad: int = 0, bigendian: bool = False) -> tuple[int, bytes]:
    """(step, data) of ``image`` (grey (H, W) or BGR (H, W, 3)) stored as ``encoding``, each row
    followed by ``pad`` bytes."""
    if encoding in ("mono8", "8UC1", "mono16", "16UC1"):
        arr = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    elif encoding in ("rgb8", "rgb16"):
        arr = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    elif encoding in ("bgra8", "8UC4"):
        arr = cv2.cvtColor(image, cv2.COLOR_BGR2BGRA)
    elif encoding == "rgba8":
        arr = cv2.cvtColor(image, cv2.COLOR_BGR2RGBA)
    else:
        arr = image
    if encoding in ("mono16", "16UC1", "rgb16") and arr.dtype != np.uint16:
        arr = arr.astype(np.uint16) * 257
    arr = np.ascontiguousarray(arr.astype(arr.dtype.newbyteorder(">" if bigendian else "<")))
    h = arr.shape[0]
    row = arr.reshape(h, -1).view(np.uint8)
    if pad:
        row = np.hstack([row, np.full((h, pad), 0xAB, np.uint8)])
    return row.shape[1], row.tobytes()


def _store(kind: str):
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC if kind == "ros1" else Stores.ROS2_HUMBLE)


def write_bag(
    path: Path,
    frames: list[np.ndarray],
    kind: str = "ros1",
    *,
    topic: str = "/camera/image_raw",
    encoding: str = "mono8",
    compressed: str | None = None,
    camera_info: dict | None = None,
    info_topic: str = "/camera/camera_info",
    pad: int = 0,
    bigendian: bool = False,
    extra_topics: dict[str, str] | None = None,
    stamps_ns: list[int] | None = None,
) -> Path:
    """Write ``frames`` to a bag at ``path`` (``kind`` in :data:`STORAGES`; a ROS 1 path ends in
    ``.bag``, a ROS 2 one is a folder). ``compressed``: ``"jpeg"`` / ``"png"`` writes CompressedImage
    messages (``topic`` then usually ends in ``/compressed``); ``camera_info``: ``fx, fy, cx, cy,
    width, height[, d, binning, roi]`` of one CameraInfo message; ``extra_topics``: topic -> message
    type (Image or String) written once each with a tiny payload."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin, Writer as Writer2

    ts = _store(kind)
    T = ts.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
    ros1 = kind == "ros1"

    def header(ns: int, seq: int):
        stamp = Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        return Header(seq=seq, stamp=stamp, frame_id="camera") if ros1 else Header(stamp=stamp, frame_id="camera")

    def ser(msg, typ: str) -> bytes:
        return ts.serialize_ros1(msg, typ) if ros1 else ts.serialize_cdr(msg, typ)

    if ros1:
        writer = Writer1(path)
    else:
        writer = Writer2(path, version=9, storage_plugin=StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3)
    img_type = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"
    with writer as w:
        conn = w.add_connection(topic, img_type, typestore=ts) if frames else None
        info_conn = w.add_connection(info_topic, "sensor_msgs/msg/CameraInfo", typestore=ts) if camera_info else None
        extra = {t: w.add_connection(t, ty, typestore=ts) for t, ty in (extra_topics or {}).items()}
        for t, ty in (extra_topics or {}).items():
            if ty == "std_msgs/msg/String":
                w.write(extra[t], T0_NS - 1, ser(T[ty](data="hello"), ty))
            else:
                w.write(extra[t], T0_NS - 1, ser(T[ty](header=header(T0_NS - 1, 0), height=1, width=1, encoding="mono8",
                                                        is_bigendian=0, step=1, data=np.zeros(1, np.uint8)), ty))
        if camera_info:
            c = camera_info
            K = np.array([c["fx"], 0, c["cx"], 0, c["fy"], c["cy"], 0, 0, 1], float)
            P = np.array([c["fx"], 0, c["cx"], 0, 0, c["fy"], c["cy"], 0, 0, 0, 1, 0], float)
            roi_x, roi_y, roi_w, roi_h = c.get("roi", (0, 0, 0, 0))
            roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=roi_x, y_offset=roi_y, height=roi_h, width=roi_w,
                                                        do_rectify=False)
            d = np.array(c.get("d", [0.0] * 5), float)
            fields = dict(header=header(T0_NS, 0), height=c["height"], width=c["width"], distortion_model="plumb_bob",
                          binning_x=c.get("binning", 0), binning_y=c.get("binning", 0), roi=roi)
            names = ("D", "K", "R", "P") if ros1 else ("d", "k", "r", "p")
            fields.update(zip(names, (d, K, np.eye(3).ravel(), P)))
            w.write(info_conn, T0_NS, ser(T["sensor_msgs/msg/CameraInfo"](**fields), "sensor_msgs/msg/CameraInfo"))
        for i, f in enumerate(frames):
            ns = stamps_ns[i] if stamps_ns is not None else T0_NS + i * STEP_NS
            record_ns = T0_NS + i * STEP_NS + 5_000_000  # received 5 ms after the stamp
            if compressed:
                ok, buf = cv2.imencode(".jpg" if compressed == "jpeg" else ".png", f)
                assert ok
                msg = T[img_type](header=header(ns, i), format=compressed, data=np.frombuffer(buf.tobytes(), np.uint8))
            else:
                step, data = raw_payload(f, encoding, pad, bigendian)
                msg = T[img_type](header=header(ns, i), height=f.shape[0], width=f.shape[1], encoding=encoding,
                                  is_bigendian=int(bigendian), step=step, data=np.frombuffer(data, np.uint8))
            w.write(conn, record_ns, ser(msg, img_type))
    return path


def write_frames_like_bag(folder: Path, frames: list[np.ndarray], compressed: str | None = None,
                          sixteen: bool = False) -> list[Path]:
    """The same frames as files named by their stamps (``<stamp>.png``, or the very JPEG bytes the
    bag holds for ``compressed="jpeg"``); ``sixteen``: as 16-bit PNGs (``* 257``, as the bag holds them)."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, f in enumerate(frames):
        ext = ".jpg" if compressed == "jpeg" else ".png"
        p = folder / f"{stamp_name(i)}{ext}"
        ok, buf = cv2.imencode(ext, f.astype(np.uint16) * 257 if sixteen else f)
        assert ok
        p.write_bytes(buf.tobytes())
        paths.append(p)
    return paths
