"""topomap.images: listing (natural sort), reading any depth/channels, truncation, sequences, video."""

from __future__ import annotations

import os
import time

import cv2
import numpy as np
import pytest
from fuzz_cases import jpeg_declaring, pgm_declaring, png_bomb, png_declaring
from map_synth import sequence, write_sequence, write_video

from topomap.errors import DatasetError
from topomap.images import (
    MAX_IMAGE_BYTES,
    MAX_WORKING_SIDE_PX,
    ImageSequence,
    decode_image,
    display_name,
    list_images,
    natural_key,
    open_sequence,
    probe_image,
    read_image,
    to_gray_u8,
    to_working_resolution,
    working_size,
)


@pytest.fixture(scope="module")
def grey():
    """A (36, 48) uint8 random texture."""
    return np.random.default_rng(3).integers(0, 256, (36, 48)).astype(np.uint8)


# ----------------------------------------------------------------------------- listing
def test_natural_sort_orders_numbers_by_value(tmp_path):
    for name in ["img10.png", "img2.png", "img1.png", "IMG3.png", "img20.png"]:
        cv2.imwrite(str(tmp_path / name), np.zeros((4, 4), np.uint8))
    (tmp_path / "notes.txt").write_text("not an image")
    (tmp_path / ".hidden.png").write_bytes(b"")
    assert [p.name for p in list_images(tmp_path)] == ["img1.png", "img2.png", "IMG3.png", "img10.png", "img20.png"]
    assert sorted(["b10", "b9", "a100"], key=natural_key) == ["a100", "b9", "b10"]


def test_list_images_errors(tmp_path):
    with pytest.raises(DatasetError, match="does not exist"):
        list_images(tmp_path / "nope")
    with pytest.raises(DatasetError, match="is empty"):
        list_images(tmp_path)
    (tmp_path / "a.txt").write_text("x")
    with pytest.raises(DatasetError, match="holds no images"):
        list_images(tmp_path)
    with pytest.raises(DatasetError, match="not a folder"):
        list_images(tmp_path / "a.txt")


# ----------------------------------------------------------------------------- to_gray_u8
def test_to_gray_u8_passes_grey_u8_through(grey):
    out = to_gray_u8(grey)
    assert out.dtype == np.uint8 and out.shape == grey.shape
    np.testing.assert_array_equal(out, grey)
    np.testing.assert_array_equal(to_gray_u8(grey[:, :, None]), grey)  # (H, W, 1)


def test_to_gray_u8_bgr_and_rgba(grey):
    bgr = np.dstack([grey, np.roll(grey, 1, 0), np.roll(grey, 2, 1)])
    expected = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    np.testing.assert_array_equal(to_gray_u8(bgr), expected)
    bgra = np.dstack([bgr, np.zeros_like(grey)])  # fully transparent alpha is dropped, not blended
    np.testing.assert_array_equal(to_gray_u8(bgra), expected)


def test_to_gray_u8_uint16_uses_bit_depth(grey):
    full = grey.astype(np.uint16) * 257  # 16-bit data spanning the range
    np.testing.assert_array_equal(to_gray_u8(full), grey)
    twelve = grey.astype(np.uint16) << 4  # a 12-bit sensor in a 16-bit container stays bright
    np.testing.assert_array_equal(to_gray_u8(twelve), grey)
    assert to_gray_u8(np.zeros((5, 5), np.uint16)).max() == 0


def test_to_gray_u8_floats(grey):
    unit = grey.astype(np.float32) / 255.0
    np.testing.assert_array_equal(to_gray_u8(unit), grey)
    wide = grey.astype(np.float64) * 4.0 - 100.0  # not in [0, 1]: min-max normalised
    out = to_gray_u8(wide)
    assert out.min() == 0 and out.max() == 255
    assert np.corrcoef(out.ravel(), grey.ravel())[0, 1] > 0.999
    np.testing.assert_array_equal(to_gray_u8(np.full((3, 3), 7.5)), np.zeros((3, 3), np.uint8))
    nan = unit.copy()
    nan[0, 0] = np.nan
    assert to_gray_u8(nan).dtype == np.uint8


def test_to_gray_u8_rejects_non_images():
    with pytest.raises(DatasetError, match="2 channels"):
        to_gray_u8(np.zeros((4, 4, 2), np.uint8))
    with pytest.raises(DatasetError, match="not an image"):
        to_gray_u8(np.zeros(10, np.uint8))


# ----------------------------------------------------------------------------- read_image
def test_read_image_any_depth_and_channels(tmp_path, grey):
    cv2.imwrite(str(tmp_path / "g16.png"), grey.astype(np.uint16) * 257)
    bgra = np.dstack([cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR), np.full_like(grey, 255)])
    cv2.imwrite(str(tmp_path / "rgba.png"), bgra)
    cv2.imwrite(str(tmp_path / "g.pgm"), grey)
    cv2.imwrite(str(tmp_path / "f.tiff"), grey.astype(np.float32) / 255.0)
    for name in ["g16.png", "rgba.png", "g.pgm", "f.tiff"]:
        img = read_image(tmp_path / name)
        assert img.dtype == np.uint8 and img.shape == grey.shape, name
        assert np.abs(img.astype(int) - grey).max() <= 1, name


def test_read_image_bad_files(tmp_path, grey):
    with pytest.raises(DatasetError, match="does not exist"):
        read_image(tmp_path / "missing.png")
    (tmp_path / "zero.jpg").write_bytes(b"")
    with pytest.raises(DatasetError, match="empty file"):
        read_image(tmp_path / "zero.jpg")
    (tmp_path / "fake.png").write_text("this is text, not a PNG")
    with pytest.raises(DatasetError, match="not a readable image"):
        read_image(tmp_path / "fake.png")
    big = cv2.resize(grey, (480, 360))
    for ext in (".jpg", ".png"):
        ok, buf = cv2.imencode(ext, big)
        data = buf.tobytes()
        (tmp_path / f"cut{ext}").write_bytes(data[: len(data) * 2 // 3])
        with pytest.raises(DatasetError, match="truncated|not a readable image"):
            read_image(tmp_path / f"cut{ext}")
        (tmp_path / f"whole{ext}").write_bytes(data)
        assert read_image(tmp_path / f"whole{ext}").shape == (360, 480)


def test_jpeg_truncation_guard(tmp_path):
    """OpenCV 4.10/4.11 decode a cut JPEG without complaint; the end-of-image check catches it
    without rejecting whole files that carry data after the image (phone motion photos, trailers)."""
    from topomap.images import _looks_truncated

    img = cv2.resize(sequence(1)[0], (320, 240))
    jpg = cv2.imencode(".jpg", img)[1].tobytes()
    thumb = cv2.imencode(".jpg", cv2.resize(img, (40, 30)))[1].tobytes()
    with_thumb = jpg[:2] + b"\xff\xfe" + (len(thumb) + 2).to_bytes(2, "big") + thumb + jpg[2:]  # COM segment

    def cut(data: bytes) -> bool:
        return _looks_truncated(np.frombuffer(data, np.uint8), tmp_path / "x.jpg")

    assert not cut(jpg) and not cut(with_thumb)
    assert cut(jpg[: len(jpg) // 2]) and cut(jpg[:-2])
    assert cut(with_thumb[: len(with_thumb) // 2])  # the thumbnail's end marker does not count
    trailer = jpg + b"\x00\x00\x00\x18ftypmp42" + bytes(4000)  # a video appended after the image
    assert not cut(trailer)
    (tmp_path / "motion.jpg").write_bytes(trailer)
    assert np.abs(read_image(tmp_path / "motion.jpg").astype(int) - img).mean() < 3


# ----------------------------------------------------------------------------- resolution
def test_working_size():
    assert working_size(768, 512, None, 480) == (768, 512)  # in range: unchanged
    assert working_size(160, 120, None, 480) == (480, 360)  # tiny camera: enlarged
    assert working_size(3072, 2048, 1024, 480) == (1024, 683)  # shrunk to --resize
    assert working_size(160, 120, None, 0) == (160, 120)  # no upscaling asked


def test_to_working_resolution(grey):
    assert to_working_resolution(grey, (48, 36)) is grey
    up = to_working_resolution(grey, (96, 72))
    assert up.shape == (72, 96) and up.dtype == np.uint8
    assert to_working_resolution(grey, (24, 18)).shape == (18, 24)


# ----------------------------------------------------------------------------- sequences
def test_folder_sequence_keeps_unreadable_frames(tmp_path):
    frames = sequence(3)
    write_sequence(tmp_path, frames)
    (tmp_path / "img1.png").write_bytes(b"broken")
    seq = open_sequence(tmp_path)
    assert seq.kind == "folder" and len(seq) == 3 and seq.names == ["img0.png", "img1.png", "img2.png"]
    got = list(seq)
    assert [f.index for f in got] == [0, 1, 2]
    assert got[1].image is None and "not a readable image" in got[1].error
    np.testing.assert_array_equal(got[2].image, frames[2])
    assert len(ImageSequence(tmp_path, every=2)) == 2


def test_list_file_sequence(tmp_path):
    write_sequence(tmp_path / "imgs", sequence(3))
    lst = tmp_path / "frames.txt"
    lst.write_text(f"# a comment\nimgs/img2.png\n\n{tmp_path / 'imgs' / 'img0.png'}\n")
    seq = open_sequence(lst)
    assert seq.kind == "list" and seq.names == ["img2.png", "img0.png"]  # list order, not sorted
    assert all(f.image is not None for f in seq)
    (tmp_path / "empty.txt").write_text("# nothing\n")
    with pytest.raises(DatasetError, match="names no images"):
        open_sequence(tmp_path / "empty.txt")


def test_video_sequence_every(tmp_path):
    frames = sequence(8, step_px=20)
    video = write_video(tmp_path / "clip.avi", frames)
    seq = open_sequence(video)
    assert seq.kind == "video" and seq.names is None
    got = list(seq)
    assert len(got) == 8 and got[3].name == "frame_000003"
    assert got[0].image.shape == frames[0].shape and got[0].image.dtype == np.uint8
    assert np.abs(got[0].image.astype(int) - frames[0]).mean() < 8  # MJPG is lossy
    half = list(open_sequence(video, every=2))
    assert [f.name for f in half] == ["frame_000000", "frame_000002", "frame_000004", "frame_000006"]
    assert [f.index for f in half] == [0, 1, 2, 3]


def test_sequence_errors(tmp_path):
    with pytest.raises(DatasetError, match="does not exist"):
        open_sequence(tmp_path / "missing")
    (tmp_path / "data.csv").write_text("a,b\n")
    with pytest.raises(DatasetError, match="neither a folder"):
        open_sequence(tmp_path / "data.csv")
    with pytest.raises(DatasetError, match="--every"):
        open_sequence(tmp_path, every=0)
    (tmp_path / "bad.avi").write_bytes(b"not a video at all")
    with pytest.raises(DatasetError, match="cannot open video"):
        open_sequence(tmp_path / "bad.avi")


def test_single_image_source(tmp_path, grey):
    cv2.imwrite(str(tmp_path / "one.png"), grey)
    seq = open_sequence(tmp_path / "one.png")
    assert seq.kind == "image" and len(seq) == 1
    np.testing.assert_array_equal(next(iter(seq)).image, grey)


def test_working_size_caps_the_enlargement():
    # a 64x32 thumbnail is not enlarged 7.5x to reach 480 px: at most 3x (interpolation invents texture)
    assert working_size(64, 32, None, 480) == (192, 96)
    assert working_size(64, 32, None, 480, max_upscale=10.0) == (480, 240)


# ----------------------------------------------------------------------------- the decoding gate
@pytest.mark.parametrize("make,size", [
    (lambda: png_bomb(30000, 30000), (30000, 30000)),  # complete and valid: 890 KB for 900 Mpx
    (lambda: png_declaring(60000, 60000), (60000, 60000)),
    (lambda: jpeg_declaring(20000, 20000, colour=True), (20000, 20000)),
    (lambda: pgm_declaring(40000, 40000), (40000, 40000)),
])
def test_bombs_are_refused_from_their_declared_size(make, size):
    data = make()
    t0 = time.perf_counter()
    with pytest.raises(DatasetError, match=f"declares {size[0]}x{size[1]} pixels, more than the 50 Mpx"):
        decode_image(data)
    assert time.perf_counter() - t0 < 1.0  # refused from the header, nothing decoded
    info = probe_image(data)
    assert (info.width, info.height) == size


def test_probe_reads_every_format_without_decoding(tmp_path, grey):
    for ext, fmt in ((".png", "PNG"), (".jpg", "JPEG"), (".bmp", "BMP"), (".tiff", "TIFF"), (".webp", "WEBP"),
                     (".pgm", "PPM"), (".gif", None)):
        if ext == ".gif":
            data, fmt = _gif(grey), "GIF"
        else:
            data = cv2.imencode(ext, grey)[1].tobytes()
        info = probe_image(data)
        assert (info.format, info.width, info.height) == (fmt, grey.shape[1], grey.shape[0]), ext
        assert decode_image(data).shape == grey.shape, ext


def test_gate_limits_and_formats(grey):
    png = cv2.imencode(".png", grey)[1].tobytes()
    h, w = grey.shape
    with pytest.raises(DatasetError, match=f"more than {w - 1}x{h}"):
        decode_image(png, max_size=(w - 1, h))
    with pytest.raises(DatasetError, match="is PNG, expected JPEG"):
        decode_image(png, formats=("JPEG",))
    with pytest.raises(DatasetError, match="is empty"):
        decode_image(b"")
    with pytest.raises(DatasetError, match="not a readable image"):
        decode_image(b"GIF89a" + bytes(20))
    assert decode_image(png, color=True).shape == (h, w, 3)


def test_decoder_warnings_stay_off_stderr(capfd, grey, monkeypatch):
    import logging

    monkeypatch.setattr(logging.getLogger("topomap"), "level", logging.WARNING)  # as the CLI runs by default
    jpg = bytearray(cv2.imencode(".jpg", cv2.resize(grey, (320, 240)))[1].tobytes())
    for i in range(5):
        jpg[len(jpg) // 2 + 97 * i] ^= 0x55  # corrupt entropy-coded data: libjpeg complains on fd 2
    assert decode_image(bytes(jpg)).shape == (240, 320)
    with pytest.raises(DatasetError):
        decode_image(cv2.imencode(".png", grey)[1].tobytes()[:-30])
    out, err = capfd.readouterr()
    assert err == "" and out == ""


def test_files_that_are_not_regular_files(tmp_path):
    (tmp_path / "dir.jpg").mkdir()
    os.mkfifo(tmp_path / "fifo.png")
    os.symlink("/dev/zero", tmp_path / "zero.jpg")
    os.symlink("loop.jpg", tmp_path / "loop.jpg")
    os.symlink("missing.jpg", tmp_path / "broken.jpg")
    for name, reason in (("dir.jpg", "is a folder"), ("fifo.png", "is a FIFO"), ("zero.jpg", "is a device"),
                         ("loop.jpg", "symbolic link loop"), ("broken.jpg", "broken symbolic link")):
        t0 = time.perf_counter()
        with pytest.raises(DatasetError, match=reason):
            read_image(tmp_path / name)
        assert time.perf_counter() - t0 < 1.0, name  # a FIFO is never waited on
    big = tmp_path / "big.png"
    with open(big, "wb") as fh:
        fh.truncate(MAX_IMAGE_BYTES + 1)  # sparse: no disk used
    with pytest.raises(DatasetError, match="more than the 256 MB topomap reads"):
        read_image(big)


def test_odd_folder_entries_are_counted_as_skipped(tmp_path, grey):
    write_sequence(tmp_path, [grey, grey], stem="img")
    (tmp_path / "dir.jpg").mkdir()
    os.mkfifo(tmp_path / "fifo.png")
    os.symlink("/dev/zero", tmp_path / "zero.jpg")
    os.symlink("loop.jpg", tmp_path / "loop.jpg")
    (tmp_path / "anim.gif").write_bytes(_gif(grey))
    (tmp_path / "notes.txt").write_text("not a frame")
    frames = list(open_sequence(tmp_path))
    errors = {f.name: f.error for f in frames if f.image is None}
    assert set(errors) == {"dir.jpg", "fifo.png", "zero.jpg", "loop.jpg"}, errors
    assert {f.name for f in frames if f.image is not None} == {"img0.png", "img1.png", "anim.gif"}
    listed = tmp_path / "list.txt"
    listed.write_text("fifo.png\nimg0.png\n/dev/zero\n")
    frames = list(open_sequence(listed))
    assert [f.image is None for f in frames] == [True, False, True]


def _gif(grey) -> bytes:
    import io

    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(grey).save(buf, "GIF")
    return buf.getvalue()


def test_list_file_that_is_a_fifo_is_refused(tmp_path):
    os.mkfifo(tmp_path / "frames.txt")
    with pytest.raises(DatasetError, match="not a regular file"):
        open_sequence(tmp_path / "frames.txt")


def test_working_size_never_exceeds_the_cap():
    assert max(working_size(30000, 30000, None, 480)) == MAX_WORKING_SIDE_PX
    assert working_size(8000, 6000, None, 480) == (4096, 3072)
    assert max(working_size(100, 100, None, 10**9, max_upscale=1e9)) == MAX_WORKING_SIDE_PX
    assert working_size(8000, 6000, 640, 480) == (640, 480)


def test_display_name_escapes_non_utf8_bytes():
    assert display_name("caf\udce9.jpg") == "caf\\xe9.jpg"
    assert display_name("café.jpg") == "café.jpg"
