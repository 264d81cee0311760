"""topomap.sources: ROS 1 / ROS 2 (sqlite3, MCAP) bags as image sources — the same map as from the
same frames as files, every raw encoding with padding and byte order, CameraInfo, stamps as names,
and one clear line for every bad bag (issue 18)."""

from __future__ import annotations

import json
import logging
import shutil
import sys
import zlib

import cv2
import numpy as np
import pytest
from bag_synth import STORAGES, T0_NS, raw_payload, stamp_name, write_bag, write_frames_like_bag
from conftest import assert_error
from map_synth import FAST, SHORT_WALK_PX, out_and_back_x, scene, window
from test_build import snapshot

pytest.importorskip("rosbags", reason="the bags extra (rosbags) is not installed")

from topomap.build import build_map  # noqa: E402
from topomap.camera import CameraIntrinsics  # noqa: E402
from topomap.errors import DatasetError, MissingExtraError  # noqa: E402
from topomap.images import open_sequence, read_image  # noqa: E402
from topomap.sources import MAX_IMAGE_PIXELS, RAW_ENCODINGS, BagSequence, camera_from_info, decode_compressed, decode_raw  # noqa: E402

CAMERA = dict(fx=410.0, fy=405.0, cx=241.5, cy=178.0, width=480, height=360, d=[-0.05, 0.01, 0.0, 0.0, 0.0])

#: Window positions of the short out-and-back walk: its return leg still closes loops, and the six
#: twin maps below build in seconds rather than a minute.
WALK_X = out_and_back_x(length_px=SHORT_WALK_PX)


def walk_frames() -> list[np.ndarray]:
    """The short out-and-back walk of map_synth (grey frames; its return leg closes loops)."""
    tex = scene(0)
    return [window(tex, x, y=40.0) for x in WALK_X]


def colour(frames: list[np.ndarray]) -> list[np.ndarray]:
    """BGR frames whose grey conversion keeps the texture (three different channels)."""
    return [np.dstack([f, np.roll(f, 7, axis=1), 255 - f]) for f in frames]


def camera_file(folder, cam=CAMERA):
    c = CameraIntrinsics(cam["fx"], cam["fy"], cam["cx"], cam["cy"], cam["width"], cam["height"], distortion=tuple(cam["d"]))
    return c.save(folder / "camera.yaml")


# ----------------------------------------------------------------------------- same map
def unsuffixed(snap: tuple) -> tuple:
    """A map snapshot with the files' extensions dropped from frame names (``<stamp>.png`` is the
    file twin of the bag frame ``<stamp>``)."""
    def bare(name: str) -> str:
        return name.rsplit(".", 1)[0] if name.endswith((".png", ".jpg")) else name

    nodes, edges, frames = snap
    return ([(i, s, f, bare(src), kp, d) for i, s, f, src, kp, d in nodes], edges,
            [(i, bare(src), n, st) for i, src, n, st in frames])


#: (storage, how the frames are stored): the three storages, each with another message kind.
CASES = [("ros1", "mono8"), ("sqlite3", "rgb8"), ("mcap", "jpeg")]


@pytest.fixture(scope="module")
def twins(tmp_path_factory):
    """For each case: the bag, the folder of the same frames as files, and both maps."""
    from topomap.camera import load_camera

    root = tmp_path_factory.mktemp("twins")
    grey = walk_frames()
    out = {}
    for storage, how in CASES:
        frames = colour(grey) if how == "rgb8" else grey
        bag = root / (f"{storage}.bag" if storage == "ros1" else storage)
        compressed = "jpeg" if how == "jpeg" else None
        write_bag(bag, frames, storage, encoding=how if how != "jpeg" else "mono8", compressed=compressed,
                  topic="/camera/image_raw/compressed" if compressed else "/camera/image_raw",
                  camera_info=CAMERA, pad=12 if how == "rgb8" else 0)
        folder = root / f"{storage}-files"
        write_frames_like_bag(folder, frames, compressed)
        cam = load_camera(camera_file(root))
        out[storage] = (bag, folder, build_map(bag, FAST), build_map(folder, FAST, cam))
    return out


@pytest.mark.slow
@pytest.mark.parametrize("storage", [s for s, _ in CASES])
def test_bag_builds_the_same_map_as_its_frames_as_files(twins, storage):
    bag, folder, from_bag, from_files = twins[storage]
    # nodes, features, edges and frames, bit for bit (names: the stamp, without the file's extension)
    assert snapshot(from_bag) == unsuffixed(snapshot(from_files))
    assert snapshot(from_bag) != snapshot(from_files)  # (the names really were compared)
    assert len(from_bag.nodes) >= 4 and from_bag.edges_by_kind()["loop"] >= 1
    assert [f.source for f in from_bag.frames[:2]] == [stamp_name(0), stamp_name(1)]
    # the intrinsics came from the CameraInfo topic, and equal the same values given as --camera
    assert from_bag.camera.source == f"{bag.name}:/camera/camera_info"
    cam_bag, cam_files = from_bag.camera.to_dict(), from_files.camera.to_dict()
    cam_bag.pop("source"), cam_files.pop("source")
    assert cam_bag == cam_files
    assert from_bag.sequences[-1]["kind"] == "bag"


@pytest.mark.slow
def test_bare_mcap_and_db3_files_read_like_their_folders(twins, tmp_path):
    bag, _, from_bag, _ = twins["mcap"]
    mcap = next(bag.glob("*.mcap"))
    assert snapshot(build_map(mcap, FAST)) == snapshot(from_bag)
    db3 = next(twins["sqlite3"][0].glob("*.db3"))
    seq = open_sequence(db3)
    assert seq.kind == "bag" and len(seq) == len(WALK_X)
    # a rosbag2 folder that lost its metadata.yaml: its one storage file is read
    lost = tmp_path / "lost"
    lost.mkdir()
    shutil.copy(mcap, lost / mcap.name)
    assert open_sequence(lost).names == seq.names


# ----------------------------------------------------------------------------- frames
@pytest.mark.parametrize("storage", STORAGES)
@pytest.mark.parametrize("encoding,pad,big", [
    ("mono8", 0, False), ("8UC1", 5, False), ("mono16", 0, False), ("mono16", 6, True), ("16UC1", 2, True),
    ("rgb8", 3, False), ("bgr8", 0, False), ("rgba8", 4, False), ("bgra8", 0, False), ("rgb16", 0, True),
])
def test_raw_encodings_read_like_the_same_image_file(tmp_path, storage, encoding, pad, big):
    grey = walk_frames()[:3]
    frames = grey if encoding in ("mono8", "8UC1", "mono16", "16UC1") else colour(grey)
    bag = tmp_path / ("b.bag" if storage == "ros1" else "b")
    write_bag(bag, frames, storage, encoding=encoding, pad=pad, bigendian=big)
    files = write_frames_like_bag(tmp_path / "files", frames, sixteen="16" in encoding)
    got = list(open_sequence(bag))
    assert [f.name for f in got] == [p.stem for p in files]
    for f, p in zip(got, files):
        assert f.error is None
        assert np.array_equal(f.image, read_image(p)), (encoding, f.name)


def test_decode_raw_other_encodings():
    rng = np.random.default_rng(0)
    grey = rng.integers(0, 256, (6, 8)).astype(np.uint8)
    bgr = rng.integers(0, 256, (6, 8, 3)).astype(np.uint8)
    # Bayer: the grey value of a demosaiced mosaic, as OpenCV computes it
    assert np.array_equal(decode_raw("bayer_rggb8", 8, 6, 8, False, grey.tobytes()), cv2.cvtColor(grey, cv2.COLOR_BayerBG2GRAY))
    # YUV 4:2:2 UYVY: luma is every second byte
    uyvy = np.dstack([rng.integers(0, 256, (6, 8)).astype(np.uint8), grey]).reshape(6, 16)
    assert np.array_equal(decode_raw("uyvy", 8, 6, 16, False, uyvy.tobytes()), grey)
    # NV12: the Y plane, then half as many rows of chroma
    nv12 = np.vstack([grey, rng.integers(0, 256, (3, 8)).astype(np.uint8)])
    assert np.array_equal(decode_raw("nv12", 8, 6, 8, False, nv12.tobytes()), grey)
    # float depth: kept as float (to_gray_u8 scales it later)
    depth = rng.random((6, 8)).astype(np.float32)
    assert np.array_equal(decode_raw("32FC1", 8, 6, 32, False, depth.tobytes()), depth)
    assert np.array_equal(decode_raw("32FC1", 8, 6, 32, True, depth.astype(">f4").tobytes()), depth)
    # the last row may come without its padding
    step, data = raw_payload(bgr, "bgr8", pad=4)
    assert np.array_equal(decode_raw("bgr8", 8, 6, step, False, data[:-4]), bgr)
    assert set(RAW_ENCODINGS) >= {"mono8", "mono16", "rgb8", "bgr8", "rgba8", "bgra8", "16UC1", "8UC3", "32FC1"}


def test_decode_raw_rejects_bad_payloads():
    with pytest.raises(DatasetError, match="encoding 'weird8' is not supported.*mono8"):
        decode_raw("weird8", 8, 6, 8, False, bytes(48))
    with pytest.raises(DatasetError, match="truncated"):
        decode_raw("mono8", 8, 6, 8, False, bytes(40))
    with pytest.raises(DatasetError, match="shorter than"):
        decode_raw("rgb8", 8, 6, 8, False, bytes(48))
    with pytest.raises(DatasetError, match="more than"):
        decode_raw("mono8", 100_000, 100_000, 100_000, False, b"")
    with pytest.raises(DatasetError, match="0x6"):
        decode_raw("mono8", 0, 6, 8, False, bytes(48))


def test_decode_compressed():
    img = walk_frames()[0]
    ok, png16 = cv2.imencode(".png", img.astype(np.uint16) * 257)
    assert np.array_equal(decode_compressed(png16.tobytes(), "mono16; png compressed mono16"), img.astype(np.uint16) * 257)
    depth = b"\x00" * 12 + png16.tobytes()  # compressedDepth: a 12-byte header before the PNG
    assert decode_compressed(depth, "16UC1; compressedDepth png").shape == img.shape
    ok, jpg = cv2.imencode(".jpg", img)
    with pytest.raises(DatasetError, match="truncated"):
        decode_compressed(jpg.tobytes()[: len(jpg) // 2], "jpeg")
    with pytest.raises(DatasetError, match="not a readable image"):
        decode_compressed(b"not an image at all", "jpeg")
    with pytest.raises(DatasetError, match="no data"):
        decode_compressed(b"", "jpeg")
    # a small payload that claims a huge image is refused before decoding
    big = np.zeros((1, 1), np.uint8)
    ok, tiny = cv2.imencode(".png", big)
    b = bytearray(tiny.tobytes())
    b[16:24] = (30_000).to_bytes(4, "big") + (30_000).to_bytes(4, "big")  # IHDR width, height
    b[29:33] = zlib.crc32(bytes(b[12:29])).to_bytes(4, "big")  # and the chunk's CRC
    with pytest.raises(DatasetError, match=f"more than the {MAX_IMAGE_PIXELS // 1_000_000} MP"):
        decode_compressed(bytes(b), "png")


def test_damaged_messages_are_skipped_frames(tmp_path):
    """A frame whose payload cannot be decoded is skipped with its reason, the rest are read."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    T = ts.types
    frames = walk_frames()[:3]
    bag = tmp_path / "d.bag"
    with Writer(bag) as w:
        conn = w.add_connection("/cam/image_raw/compressed", "sensor_msgs/msg/CompressedImage", typestore=ts)
        for i, f in enumerate(frames):
            data = cv2.imencode(".jpg", f)[1].tobytes()
            if i == 1:
                data = data[: len(data) // 2]
            hdr = T["std_msgs/msg/Header"](seq=i, stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=i), frame_id="")
            msg = T["sensor_msgs/msg/CompressedImage"](header=hdr, format="jpeg", data=np.frombuffer(data, np.uint8))
            w.write(conn, T0_NS + i, ts.serialize_ros1(msg, "sensor_msgs/msg/CompressedImage"))
    got = list(open_sequence(bag))
    assert [f.image is None for f in got] == [False, True, False]
    assert "truncated" in got[1].error
    m = build_map(bag, FAST)
    assert m.sequences[-1]["frames_skipped"] == 1


def test_names_from_stamps_record_time_and_duplicates(tmp_path):
    frames = walk_frames()[:4]
    bag = tmp_path / "s.bag"
    write_bag(bag, frames, "ros1", stamps_ns=[0, T0_NS, T0_NS, T0_NS + 7])  # unset, twice the same, +7 ns
    seq = open_sequence(bag)
    record0 = T0_NS + 5_000_000  # the first message's record time: its header stamp is zero
    assert seq.names == [f"{record0 // 10**9}.{record0 % 10**9:09d}", stamp_name(0), stamp_name(0) + "-1",
                         "1700000000.000000007"]
    assert [f.name for f in seq] == seq.names
    assert list(seq)[1].path == f"{bag}#/camera/image_raw@{T0_NS + 100_000_000 + 5_000_000}"


def test_every_keeps_every_nth_message(tmp_path):
    frames = walk_frames()[:7]
    bag = tmp_path / "e"
    write_bag(bag, frames, "mcap")
    seq = open_sequence(bag, every=3)
    assert len(seq) == 3 and seq.names == [stamp_name(i) for i in (0, 3, 6)]
    assert [f.index for f in seq] == [0, 1, 2]
    assert np.array_equal(list(seq)[1].image, frames[3])


# ----------------------------------------------------------------------------- camera
def _info(**over):
    from types import SimpleNamespace

    roi = SimpleNamespace(x_offset=0, y_offset=0, width=0, height=0)
    base = dict(K=np.array([400.0, 0, 320, 0, 400, 240, 0, 0, 1]), D=np.zeros(5), distortion_model="plumb_bob",
                width=640, height=480, binning_x=0, binning_y=0, roi=roi)
    base.update(over)
    return SimpleNamespace(**base)


def test_camera_from_info_binning_roi_and_uncalibrated(caplog):
    cam = camera_from_info(_info(D=np.array([-0.1, 0.02, 0.001, 0.0, 0.003])), "info")
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == (400, 400, 320, 240, 640, 480)
    assert cam.distortion == (-0.1, 0.02, 0.001, 0.0, 0.003) and cam.source == "info"
    from types import SimpleNamespace

    roi = SimpleNamespace(x_offset=100, y_offset=40, width=320, height=240)
    c = camera_from_info(_info(roi=roi))
    assert (c.cx, c.cy, c.width, c.height) == (220, 200, 320, 240)
    b = camera_from_info(_info(binning_x=2, binning_y=2))
    assert (b.fx, b.width, b.height) == (200, 320, 240) and b.cx == pytest.approx((320 + 0.5) / 2 - 0.5)
    with caplog.at_level(logging.WARNING, logger="topomap"):
        assert camera_from_info(_info(K=np.zeros(9))) is None
        fish = camera_from_info(_info(distortion_model="equidistant", D=np.array([0.1, 0, 0, 0])))
    assert "no calibration" in caplog.text and "equidistant" in caplog.text
    assert fish.distortion == (0.0,) * 5


def test_camera_info_topic_is_found_by_namespace(tmp_path):
    frames = walk_frames()[:2]
    bag = tmp_path / "n.bag"
    write_bag(bag, frames, "ros1", topic="/robot/front/image_raw/compressed", compressed="png",
              camera_info=CAMERA, info_topic="/robot/front/camera_info")
    seq = open_sequence(bag)
    assert seq.camera.source == "n.bag:/robot/front/camera_info" and seq.camera.fx == CAMERA["fx"]
    assert np.array_equal(list(seq)[0].image, frames[0])
    plain = tmp_path / "plain.bag"
    write_bag(plain, frames, "ros1")
    assert open_sequence(plain).camera is None
    assert build_map(plain, FAST).camera.source == "default"


# ----------------------------------------------------------------------------- bad bags
@pytest.fixture(scope="module")
def small_bags(tmp_path_factory):
    root = tmp_path_factory.mktemp("smallbags")
    frames = walk_frames()[:3]
    write_bag(root / "two.bag", frames, "ros1", extra_topics={"/cam2/image_raw": "sensor_msgs/msg/Image"})
    write_bag(root / "text.bag", [], "ros1", extra_topics={"/chatter": "std_msgs/msg/String"})
    write_bag(root / "weird.bag", frames, "ros1", encoding="weird8")
    write_bag(root / "good", frames, "mcap")
    data = (root / "two.bag").read_bytes()
    (root / "cut.bag").write_bytes(data[: len(data) // 2])
    (root / "junk.mcap").write_bytes(np.random.default_rng(1).bytes(4000))
    (root / "empty.db3").write_bytes(b"")
    return root


def test_bad_bags_raise_one_clear_error(small_bags):
    r = small_bags
    with pytest.raises(DatasetError, match=r"2 image topics: /cam2/image_raw \(sensor_msgs/Image, 1 messages\); "
                                           r"/camera/image_raw \(sensor_msgs/Image, 3 messages\); choose one with --topic"):
        open_sequence(r / "two.bag")
    assert len(open_sequence(r / "two.bag", topic="/cam2/image_raw")) == 1
    with pytest.raises(DatasetError, match=r"no image topic '/nope'; its image topics: /cam2/image_raw"):
        open_sequence(r / "two.bag", topic="/nope")
    with pytest.raises(DatasetError, match=r"text.bag has no image topic .*it has: /chatter \(std_msgs/String\)"):
        open_sequence(r / "text.bag")
    with pytest.raises(DatasetError, match="encoding 'weird8' is not supported"):
        open_sequence(r / "weird.bag")
    with pytest.raises(DatasetError, match="cut.bag is not a readable ROS bag .*rosbag reindex"):
        open_sequence(r / "cut.bag")
    with pytest.raises(DatasetError, match="junk.mcap is not a readable ROS bag"):
        open_sequence(r / "junk.mcap")
    with pytest.raises(DatasetError, match="empty.db3 is not a readable ROS bag"):
        open_sequence(r / "empty.db3")
    images = r / "images"
    write_frames_like_bag(images, walk_frames()[:1])
    with pytest.raises(DatasetError, match="--topic is for ROS bags"):
        open_sequence(images, topic="/camera/image_raw")
    with pytest.raises(DatasetError, match="no metadata.yaml and 2 storage files"):
        open_sequence(r)  # junk.mcap and empty.db3 beside each other
    with pytest.raises(DatasetError, match="--every"):
        BagSequence(r / "good", every=0)


def test_missing_bags_extra_says_how_to_install(small_bags, monkeypatch):
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)  # import fails as without the extra
    with pytest.raises(MissingExtraError, match=r"pip install 'appearance-topomap\[bags\]'"):
        open_sequence(small_bags / "good")


# ----------------------------------------------------------------------------- CLI
@pytest.mark.slow
def test_cli_build_localize_and_eval_from_bags(twins, runner, cli_app, tmp_path):
    bag, folder, from_bag, _ = twins["ros1"]
    out = tmp_path / "m.topomap"
    r = runner.invoke(cli_app, ["build", str(bag), "--topic", "/camera/image_raw", "-o", str(out), "--max-features", "500",
                                "--json"])
    assert r.exit_code == 0, r.output
    summary = json.loads(r.stdout)
    assert summary["frames_read"] == len(WALK_X) and summary["nodes"] >= 4
    r = runner.invoke(cli_app, ["info", str(out), "--json"])
    assert json.loads(r.stdout)["sequence_sources"] == [str(bag)]
    # the second storage's bag (same frames in colour) as queries, topic omitted: its only one
    query = twins["sqlite3"][0]
    r = runner.invoke(cli_app, ["localize", str(out), str(query), "--json"])
    assert r.exit_code == 0, r.output
    rows = json.loads(r.stdout)
    assert [row["query"] for row in rows] == [stamp_name(i) for i in range(len(rows))]
    r = runner.invoke(cli_app, ["eval", str(out), str(query), "--topic", "/camera/image_raw", "--ground-truth", "same-name",
                                "--tolerance", "1", "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["recall_at_1"] > 0.5  # colour frames of the very same walk (grey differs)


def test_cli_bad_bags_are_one_line(small_bags, runner, cli_app, tmp_path, monkeypatch):
    out = tmp_path / "m.topomap"
    r = runner.invoke(cli_app, ["build", str(small_bags / "two.bag"), "-o", str(out)])
    assert_error(r, "2 image topics", "/cam2/image_raw", "/camera/image_raw", "choose one with --topic")
    assert_error(runner.invoke(cli_app, ["build", str(small_bags / "text.bag"), "-o", str(out)]), "no image topic")
    assert_error(runner.invoke(cli_app, ["build", str(small_bags / "cut.bag"), "-o", str(out)]), "not a readable ROS bag")
    assert_error(runner.invoke(cli_app, ["build", str(small_bags / "weird.bag"), "-o", str(out)]), "'weird8' is not supported")
    assert not out.exists()
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)
    assert_error(runner.invoke(cli_app, ["build", str(small_bags / "good"), "-o", str(out)]),
                 "pip install 'appearance-topomap[bags]'")
