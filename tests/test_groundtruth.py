"""topomap.groundtruth: poses CSV (planar and 3-D camera centres) -> floor-plan positions."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import dataset

from topomap.errors import DatasetError
from topomap.groundtruth import read_poses


def test_planar_poses(tmp_path):
    p = tmp_path / "poses.csv"
    p.write_text("image,x,z,theta\nimgs/a.png,1.0,2.0,0.5\nb.png,-1,0.25,3\n")
    t = read_poses(p)
    assert t.planar and t.names == ("a.png", "b.png")  # keyed by file name
    assert "a.png" in t and "c.png" not in t
    np.testing.assert_allclose(t["b.png"], [-1.0, 0.25, 3.0])
    pos = t.positions_2d()
    np.testing.assert_allclose(pos["a.png"], [1.0, 2.0])
    q = tmp_path / "xz.csv"
    q.write_text("frame,x,z\nf1,0,1\n")
    np.testing.assert_allclose(read_poses(q)["f1"], [0.0, 1.0, 0.0])  # missing theta stored as 0


def test_castle_camera_centres_project_to_the_ground_plane():
    t = read_poses(dataset("castle-p30") / "poses_camera_to_world.csv")
    assert not t.planar and len(t.names) == 30 and t.values.shape == (30, 3)
    pos = t.positions_2d()
    xy = np.array([pos[n] for n in t.names])
    # projection on the two principal axes preserves horizontal distances of a walk at constant height:
    # PROVENANCE.md: frame 29 stands 0.78 m from frame 1
    d3 = np.linalg.norm(t["0029.jpg"] - t["0001.jpg"])
    d2 = np.linalg.norm(pos["0029.jpg"] - pos["0001.jpg"])
    assert d3 == pytest.approx(0.78, abs=0.02) and d2 == pytest.approx(d3, abs=0.1)
    assert np.ptp(xy, axis=0).min() > 10.0  # a courtyard, not a line


def test_bad_pose_files(tmp_path):
    with pytest.raises(DatasetError, match="does not exist"):
        read_poses(tmp_path / "none.csv")
    (tmp_path / "empty.csv").write_text("image,x,z\n")
    with pytest.raises(DatasetError, match="no rows"):
        read_poses(tmp_path / "empty.csv")
    (tmp_path / "nokey.csv").write_text("x,z\n1,2\n")
    with pytest.raises(DatasetError, match="'image' column"):
        read_poses(tmp_path / "nokey.csv")
    (tmp_path / "cols.csv").write_text("image,a,b\nx.png,1,2\n")
    with pytest.raises(DatasetError, match="needs columns"):
        read_poses(tmp_path / "cols.csv")
    (tmp_path / "nan.csv").write_text("image,x,z\nx.png,1,oops\n")
    with pytest.raises(DatasetError, match="line 2"):
        read_poses(tmp_path / "nan.csv")
