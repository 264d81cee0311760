"""topomap.alignment and the aligned links of topomap.graph: an appended experience linked to the map's
others by sequence alignment where only appearance matches; the links are places, not edges."""

from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pytest

from topomap.build import build_map
from topomap.camera import CameraIntrinsics
from topomap.config import BuildConfig, CalibrationConfig
from topomap.errors import ConfigError, MapFormatError
from topomap.graph import ALIGNED_CONFIDENCE, ALIGNED_LINKS, Edge, EdgeKind, TopoMap
from topomap.localize import Localizer
from topomap.plan import Planner
from topomap.store import load_map, save_map

from conftest import dataset
from test_graph import node


@pytest.fixture
def two_runs():
    """Experience 0: nodes 0-1-2; experience 1: nodes 3-4-5, not joined by any edge."""
    m = TopoMap(camera=CameraIntrinsics.default(100, 80))
    for i in range(6):
        m.add_node(node(i, seq=i // 3))
    for a in (0, 1, 3, 4):
        m.add_edge(Edge(a, a + 1, EdgeKind.SEQUENTIAL, 100, 0.5))
    return m


def test_aligned_links_join_places_not_edges(two_runs):
    m = two_runs
    assert m.aligned_links() == [] and m.place_ids()[4] == 4
    m.set_aligned_links([(4, 1, 0.97), (3, 0, 0.96)])
    assert m.aligned_links() == [(0, 3, pytest.approx(0.96)), (1, 4, pytest.approx(0.97))]
    assert m.place_ids()[4] == 1 and m.place_ids()[3] == 0 and m.place_ids()[5] == 5
    assert m.linked(4) == [1, 3, 5] and m.neighbours(4) == [3, 5]  # the calibration's neighbourhoods
    assert m.experiences()[1]["aligned"] == {0: 2} and m.experiences()[1]["links"] == {}
    assert len(m.components()) == 2  # the graph (what the planner drives along) is unchanged
    assert Planner(m).route(0, 2).nodes == [0, 1, 2]
    m.set_aligned_links([])
    assert ALIGNED_LINKS not in m.arrays and m.place_ids()[4] == 4


@pytest.mark.parametrize("pairs, conf, what", [
    (np.array([[1, 4]], np.int64), None, "malformed"),
    (np.array([1, 4], np.int64), np.array([0.9], np.float32), "malformed"),
    (np.array([[1, 4]], np.float64), np.array([0.9], np.float32), "malformed"),
    (np.array([[1, 4]], np.int64), np.array([np.nan], np.float32), "malformed"),
    (np.array([[1, 4]], np.int64), np.array([0.9, 0.8], np.float32), "malformed"),
    (np.array([[1, 99]], np.int64), np.array([0.9], np.float32), "does not join"),
    (np.array([[1, 2]], np.int64), np.array([0.9], np.float32), "does not join"),  # one experience
])
def test_a_strangers_malformed_links_are_a_map_format_error(two_runs, pairs, conf, what):
    two_runs.arrays[ALIGNED_LINKS] = pairs
    if conf is not None:
        two_runs.arrays[ALIGNED_CONFIDENCE] = conf
    with pytest.raises(MapFormatError, match=what):
        two_runs.place_ids()


def test_config_validates_the_link_threshold():
    assert BuildConfig(align_min_confidence=None).align_min_confidence is None
    for bad in (0.0, 1.5, -0.1):
        with pytest.raises(ConfigError, match="align_min_confidence"):
            BuildConfig(align_min_confidence=bad)


def _nordland(tmp_path, season: str, first: int, count: int):
    src = dataset("nordland-64x32") / season
    out = tmp_path / f"{season}-{first}"
    out.mkdir()
    for p in sorted(src.glob("*.png"))[first:first + count]:
        shutil.copy(p, out / p.name)
    return out


@pytest.fixture(scope="module")
def summer_map(tmp_path_factory):
    """A map of Nordland summer frames 0-299 (appearance only: 64x32 images carry no keypoints)."""
    tmp = tmp_path_factory.mktemp("summer")
    path = tmp / "summer.topomap"
    save_map(build_map(_nordland(tmp, "summer", 0, 300)), path)
    return path


def uncalibrated_append(base: TopoMap) -> TopoMap:
    """``base`` whose build config skips the calibration refit after an append: the links are made
    before it (with the summer map's own calibration) and it is not what these tests check."""
    return dataclasses.replace(base, config=dataclasses.replace(base.config, calibration=CalibrationConfig(enabled=False)))


@pytest.mark.slow
def test_winter_appended_to_a_summer_map_is_aligned_where_the_filter_is_sure(tmp_path, summer_map):
    """An appearance-only map (no keypoints to verify): only alignment can link the seasons, and
    every link it makes must show the same place (the same frame name: the videos are GPS-synced)."""
    m = build_map(_nordland(tmp_path, "winter", 0, 300), base=uncalibrated_append(load_map(summer_map, images=True)))
    links = m.aligned_links()
    new = {n for n in m.nodes if m.nodes[n].sequence == 1}
    assert m.sequences[-1]["aligned_links_added"] == len(links) >= 0.05 * len(new)
    wrong = [(a, b) for a, b, _ in links if m.nodes[a].source != m.nodes[b].source
             and abs(_index(m.nodes[a].source) - _index(m.nodes[b].source)) > 10]  # 1 frame = 10 video frames
    assert not wrong
    # localization answers the shared place whichever experience matched
    loc = Localizer(m)
    a, b, _ = links[len(links) // 2]
    assert loc._place[b] == loc._place[a] == min(a, b)
    path = tmp_path / "two.topomap"
    save_map(m, path)
    assert load_map(path).aligned_links() == links


def _index(name: str) -> int:
    return int(name.split("-")[-1].split(".")[0])


@pytest.mark.slow
def test_a_foreign_run_is_not_aligned(tmp_path, summer_map):
    """Frames of another railway stretch (Nordland frames 600-899) appended to a map of 0-299: no link."""
    m = build_map(_nordland(tmp_path, "winter", 600, 300), base=uncalibrated_append(load_map(summer_map)))
    assert m.aligned_links() == []
