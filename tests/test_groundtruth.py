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


# ============================================================================= place correspondences
from topomap.camera import CameraIntrinsics  # noqa: E402
from topomap.features import Features  # noqa: E402
from topomap.graph import FrameRecord, Node, TopoMap  # noqa: E402
from topomap.groundtruth import PoseTable, from_poses, read_correspondences, same_name  # noqa: E402


def corridor_like_map(skipped: tuple[int, ...] = ()) -> TopoMap:
    """Sequence 0: frames 000..009.jpg, two per node (node i: frames 2i, 2i+1), ``skipped`` frames
    unreadable; sequence 1 (an --append run): frames b0..b3.jpg in node 5."""
    m = TopoMap(camera=CameraIntrinsics.default(64, 48))
    feats, thumb = Features.empty("orb", (64, 48)), np.zeros((4, 4), np.uint8)
    for i in range(10):
        node = None if i in skipped else i // 2
        if node is not None and node not in m.nodes:
            m.add_node(Node(node, 0, i, f"{i:03d}.jpg", feats, thumb))
        m.frames.append(FrameRecord(i, 0, i, f"{i:03d}.jpg", node, "ok" if node is not None else "unreadable"))
    m.add_node(Node(5, 1, 10, "b0.jpg", feats, thumb))
    for j in range(4):
        m.frames.append(FrameRecord(10 + j, 1, j, f"b{j}.jpg", 5))
    return m


def node_frames(m: TopoMap) -> dict[int, set[str]]:
    out: dict[int, set[str]] = {n: set() for n in m.nodes}
    for f in m.frames:
        if f.node is not None:
            out[f.node].add(f.source)
    return out


def test_correspondences_by_index_like_the_corridor(tmp_path):
    p = tmp_path / "gt.csv"
    p.write_text("query_file,query_idx,matching_ref_indices\nquery/q0.jpg,0,0;1;2\nquery/q1.jpg,1,3\nq2.jpg,2,\n")
    m = corridor_like_map()
    gt = read_correspondences(p, m)
    assert gt.matches == {"q0.jpg": frozenset({"000.jpg", "001.jpg", "002.jpg"}), "q1.jpg": frozenset({"003.jpg"}),
                          "q2.jpg": frozenset()}
    assert "q0.jpg" in gt and "query/q0.jpg" not in gt  # keyed by file name
    # indices are positions in the first sequence, not in the appended one
    assert gt.correct_nodes("q0.jpg", node_frames(m)) == {0, 1}
    assert gt.correct_nodes("q1.jpg", node_frames(m)) == {1}
    assert gt.correct_nodes("q2.jpg", node_frames(m)) == set() and gt.correct_nodes("nope.jpg", node_frames(m)) == set()


def test_correspondences_by_file_name(tmp_path):
    p = tmp_path / "gt.csv"
    p.write_text("query,matching_ref_files\na.png,ref/004.jpg;b2.jpg\nb.png,\n")
    m = corridor_like_map()
    gt = read_correspondences(p, m)
    assert gt.matches["a.png"] == {"004.jpg", "b2.jpg"} and gt.matches["b.png"] == frozenset()
    assert gt.correct_nodes("a.png", node_frames(m)) == {2, 5}


def test_correspondences_may_name_a_skipped_reference_frame(tmp_path):
    p = tmp_path / "gt.csv"
    p.write_text("query_file,matching_ref_indices\nq0.jpg,2;3\nq1.jpg,3\n")
    m = corridor_like_map(skipped=(3,))
    gt = read_correspondences(p, m)  # frame 3 was unreadable: known, represented by no node
    assert gt.correct_nodes("q0.jpg", node_frames(m)) == {1}
    assert gt.correct_nodes("q1.jpg", node_frames(m)) == set()


@pytest.mark.parametrize("text, message", [
    ("query_file,matching_ref_indices\nq0.jpg,1;12;40\nq1.jpg,99\nq2.jpg,50\nq3.jpg,60\n",
     r"names frame indices that are not in the map \(e\.g\. 12, 40, 50\); the map's first sequence has 10 frames"),
    ("query_file,matching_ref_files\nq0.jpg,000.jpg;zz1.jpg\nq1.jpg,zz2.jpg;zz3.jpg;zz4.jpg\n",
     r"names 4 frame\(s\) that are not in the map \(e\.g\. zz1\.jpg, zz2\.jpg, zz3\.jpg\); is it the ground truth"),
    ("query_file,matching_ref_indices\nq0.jpg,1;two\n", r"line 2: 'two' is not a frame index"),
    ("image,x,z\na.png,1,2\n", r"is not a correspondence CSV.*columns found: image, x, z"),
    ("query_file,matching_ref_indices\n", "has no rows"),
])
def test_bad_correspondence_files(tmp_path, text, message):
    p = tmp_path / "gt.csv"
    p.write_text(text)
    with pytest.raises(DatasetError, match=message) as e:
        read_correspondences(p, corridor_like_map())
    assert "\n" not in str(e.value)


def test_same_name_with_tolerance():
    m = corridor_like_map(skipped=(5,))
    gt = same_name(["004.jpg", "b1.jpg", "elsewhere.jpg", "005.jpg"], m)
    assert gt.matches["004.jpg"] == {"004.jpg"} and gt.matches["b1.jpg"] == {"b1.jpg"}
    assert gt.matches["elsewhere.jpg"] == frozenset()  # not a frame of the map: no true match
    assert gt.correct_nodes("005.jpg", node_frames(m)) == set()  # skipped frame: no node shows it
    wide = same_name(["004.jpg", "000.jpg", "005.jpg", "b3.jpg"], m, tolerance=1)
    assert wide.matches["004.jpg"] == {"003.jpg", "004.jpg", "005.jpg"}
    assert wide.matches["000.jpg"] == {"000.jpg", "001.jpg"}  # clipped at the start
    assert wide.matches["b3.jpg"] == {"b2.jpg", "b3.jpg"}  # within its own sequence only
    assert wide.correct_nodes("005.jpg", node_frames(m)) == {2, 3}  # neighbours of a skipped frame
    with pytest.raises(DatasetError, match="no query file name is a frame of the map"):
        same_name(["x.png", "y.png"], m)


def test_from_poses_planar_and_3d():
    m = corridor_like_map()
    names = tuple(f.source for f in m.frames)
    xs = np.array([float(f.index) if f.sequence == 0 else 100.0 + f.index for f in m.frames])  # 1 m apart
    planar = PoseTable(names, np.c_[xs, np.zeros_like(xs), np.zeros_like(xs)], True)
    queries = PoseTable(("qa.png", "qb.png", "qc.png"), np.array([[2.2, 0.5, 1.0], [101.0, 0.0, 0.0], [50.0, 0.0, 0.0]]), True)
    gt = from_poses(queries, planar, m, radius_m=1.2)
    # floor-plan distance (theta ignored): 0.54 m to 002, 0.94 m to 003, 1.30 m to 001 (outside)
    assert gt.matches["qa.png"] == {"002.jpg", "003.jpg"}
    assert gt.matches["qc.png"] == frozenset()
    assert gt.matches["qb.png"] == {"b0.jpg", "b1.jpg", "b2.jpg"}
    centres = PoseTable(names, np.c_[xs, np.zeros_like(xs), np.zeros_like(xs)], False)
    q3 = PoseTable(("qa.png",), np.array([[4.0, 0.0, 0.9]]), False)
    assert from_poses(q3, centres, m, radius_m=1.0).matches["qa.png"] == {"004.jpg"}  # 3-D: |(0, 0, .9)| < 1
    with pytest.raises(DatasetError, match="--radius must be positive"):
        from_poses(queries, planar, m, radius_m=0)
    with pytest.raises(DatasetError, match="both be planar"):
        from_poses(q3, planar, m, radius_m=1.0)
    partial = PoseTable(names[:4], planar.values[:4], True)
    with pytest.raises(DatasetError, match=r"map poses lack 10 of the map's frames \(e\.g\. 004\.jpg"):
        from_poses(queries, partial, m, radius_m=1.0)
