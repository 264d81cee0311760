"""topomap.self_supervision: the calibration's queries are seeded per keyframe, so the fit is the
same in-process and over worker processes, and a keyframe's samples do not depend on the others."""

from __future__ import annotations

import dataclasses
import pickle

import numpy as np
import pytest
from map_synth import scene, window, write_sequence

from topomap.build import build_map
from topomap.config import BuildConfig, FeatureConfig, LocalizeConfig
from topomap.localize import Localizer
from topomap.parallel import DaskExecutor, InlineExecutor, ProcessExecutor
from topomap.self_supervision import (
    _without_images,
    calibrate_map,
    keyframe_rng,
    keyframe_samples,
    single_samples,
)

XS = np.arange(0.0, 2400.0, 120.0)
CONFIG = BuildConfig(features=FeatureConfig(max_features=400), vocabulary_words=2048, keyframe_min_ratio=0.5)


@pytest.fixture(scope="module")
def walk_map(tmp_path_factory):
    folder = tmp_path_factory.mktemp("walk")
    write_sequence(folder, [window(scene(4, width=4000), x, y=40.0) for x in XS])
    m = build_map(folder, CONFIG)
    assert len(m.nodes) >= 12 and "calibration" not in m.meta  # too small for the build to calibrate
    return m


def fresh(m):
    return dataclasses.replace(m, meta=dict(m.meta))


def test_the_same_calibration_on_worker_processes(walk_map):
    inline, pooled = fresh(walk_map), fresh(walk_map)
    cal = calibrate_map(inline, queries=12, seed=3)
    with ProcessExecutor(2) as ex:  # 4 shares of 3 keyframes on 2 workers
        cal_pool = calibrate_map(pooled, queries=12, seed=3, executor=ex)
    assert cal_pool == cal and pooled.meta["calibration"] == inline.meta["calibration"]
    assert cal.fitted_for["samples"] >= 36 and 0 < cal.fitted_for["right"] < cal.fitted_for["samples"]
    # another seed draws other queries: the fit is seeded, not fixed
    assert calibrate_map(fresh(walk_map), queries=12, seed=4) != cal


def test_a_keyframes_samples_do_not_depend_on_the_others(walk_map):
    loc = Localizer(walk_map, LocalizeConfig(use_calibration=False))
    a, b = sorted(walk_map.nodes)[2], sorted(walk_map.nodes)[5]
    alone = keyframe_samples(loc, b, keyframe_rng(0, b))
    together = single_samples(loc, [a, b], 0)
    assert len(alone) == 4 and together.kinds == ["nearby", "left out", "aliased", "foreign"] * 2
    assert together.rows[4:] == [[float(ev.get(f, 0.0)) for f in together.features] for ev, _, _ in alone]
    assert together.labels[4:] == [right for _, right, _ in alone]


def test_a_worker_gets_the_images_of_its_keyframes_only(walk_map):
    keep = set(sorted(walk_map.nodes)[:3])
    light = _without_images(walk_map, keep)
    assert {n for n, v in light.nodes.items() if v.image_data is not None} == keep and light.frames == []
    assert all(light.nodes[n].features is walk_map.nodes[n].features for n in walk_map.nodes)
    assert all(v.image_data is not None for v in walk_map.nodes.values())  # the map itself keeps them


class RecordingExecutor(InlineExecutor):
    """In this process, as if it had four workers, sharing values as the process pool does (a file
    each worker reads once); records the pickled size of every task and each shared value."""

    workers = 4

    def __init__(self):
        self.task_bytes: list[int] = []
        self.shared_bytes: list[int] = []

    def shared(self, value):
        self.shared_bytes.append(len(pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL)))
        return ProcessExecutor.shared(self, value)

    def map(self, fn, items, *, window=None):
        assert window is not None and window <= self.workers  # no more shares in flight than workers
        for item in items:
            self.task_bytes.append(len(pickle.dumps(item, protocol=pickle.HIGHEST_PROTOCOL)))
            yield fn(item)


def test_the_map_goes_to_the_workers_once_not_with_every_share(walk_map):
    ex = RecordingExecutor()
    cal = calibrate_map(fresh(walk_map), queries=12, seed=3, executor=ex)
    assert cal == calibrate_map(fresh(walk_map), queries=12, seed=3)
    assert len(ex.shared_bytes) == 1 and len(ex.task_bytes) == 8  # one map, 8 shares of 1-2 keyframes
    map_bytes = len(pickle.dumps(walk_map, protocol=pickle.HIGHEST_PROTOCOL))
    assert ex.shared_bytes[0] > map_bytes / 10  # the shared value is the map (without most images)
    assert max(ex.task_bytes) < 4000 < map_bytes / 100  # a share is node ids and the configuration


def test_the_same_calibration_on_dask(walk_map):
    with DaskExecutor(None, 2, processes=False) as ex:
        cal = calibrate_map(fresh(walk_map), queries=12, seed=3, executor=ex)
    assert cal == calibrate_map(fresh(walk_map), queries=12, seed=3)
