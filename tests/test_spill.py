"""topomap.spill: keyframe payloads on disk during a build, read back through a bounded working set."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from topomap.features import Features
from topomap.spill import Spill, SpilledBytes, SpilledFeatures, as_bytes


def _features(n: int, seed: int, kind: str = "orb") -> Features:
    rng = np.random.default_rng(seed)
    if kind == "sift":
        desc = rng.random((n, 128), dtype=np.float32)
    else:
        desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    return Features(rng.random((n, 2), dtype=np.float32) * 300, desc, kind, (320, 240))


@pytest.mark.parametrize("kind", ["orb", "sift"])
def test_spilled_features_read_back_exactly_and_pickle_as_plain_features(kind):
    spill = Spill(working_set=2)
    originals = [_features(n, i, kind) for i, n in enumerate((500, 0, 37))]
    spilled = [spill.put_features(f) for f in originals]
    for f, s in zip(originals, spilled):
        assert isinstance(s, SpilledFeatures) and isinstance(s, Features)
        assert len(s) == len(f) and s.kind == f.kind and s.image_size == f.image_size
        for name in ("keypoints", "descriptors"):
            a, b = getattr(f, name), getattr(s, name)
            assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
        back = pickle.loads(pickle.dumps(s))  # what a worker process receives
        assert type(back) is Features and back.descriptors.tobytes() == f.descriptors.tobytes()
        assert back.descriptors.flags.writeable  # a copy, not a view of the spill's buffer
    assert spill.bytes_written == sum(f.keypoints.nbytes + f.descriptors.nbytes for f in originals)


def test_the_working_set_is_bounded_and_spilled_arrays_are_read_only():
    spill = Spill(working_set=3)
    spilled = [spill.put_features(_features(100, i)) for i in range(10)]
    for s in spilled:
        s.descriptors
    assert len(spill._lru) == 3  # only the last three read are held
    first = spilled[-1].descriptors
    assert spilled[-1].descriptors is first  # a hit reads nothing again
    with pytest.raises(ValueError):
        first[0, 0] = 1  # the cached arrays are shared: nobody may write into them
    spilled[0].keypoints  # an evicted one reads back the same values
    assert spilled[0].keypoints.tobytes() == _features(100, 0).keypoints.tobytes()
    with pytest.raises(ValueError, match="at least one"):
        Spill(working_set=0)


def test_spilled_bytes():
    spill = Spill()
    data = bytes(range(256)) * 10
    s = spill.put_bytes(data)
    assert isinstance(s, SpilledBytes) and len(s) == len(data)
    assert bytes(s) == data and as_bytes(s) == data and as_bytes(data) is data and as_bytes(None) is None
    assert pickle.loads(pickle.dumps(s)) == data


def test_a_built_map_holds_its_new_keyframes_on_disk_and_saves_the_same_rows(tmp_path):
    from map_synth import FAST, SHORT_WALK_PX, write_out_and_back

    from topomap.build import build_map
    from topomap.store import load_map, save_map

    write_out_and_back(tmp_path / "walk", length_px=SHORT_WALK_PX)
    m = build_map(tmp_path / "walk", FAST)
    assert m.nodes and all(isinstance(n.features, SpilledFeatures) for n in m.nodes.values())
    assert all(isinstance(n.image_data, SpilledBytes) for n in m.nodes.values())
    path = save_map(m, tmp_path / "m.topomap")
    back = load_map(path, images=True)
    for nid, n in m.nodes.items():
        b = back.nodes[nid]
        assert type(b.features) is Features  # a loaded map holds plain arrays
        assert b.features.descriptors.tobytes() == n.features.descriptors.tobytes()
        assert b.features.keypoints.tobytes() == n.features.keypoints.tobytes()


def test_a_full_disk_is_one_clear_error(monkeypatch, tmp_path):
    import os

    from topomap.errors import TopomapError

    spill = Spill(directory=str(tmp_path))

    def full(fd, data, at):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "pwrite", full)
    with pytest.raises(TopomapError, match=r"cannot hold the build's keyframes on disk in .*No space left.*TMPDIR"):
        spill.put_bytes(b"x" * 10)
    monkeypatch.setattr(os, "pwrite", lambda fd, data, at: len(data) - 1)  # a short write: the disk filled up
    with pytest.raises(TopomapError, match="the disk is full"):
        spill.put_bytes(b"x" * 10)
