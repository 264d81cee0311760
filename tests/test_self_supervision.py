"""topomap.self_supervision: the calibration's queries are seeded per keyframe, so the fit is the
same in-process and over worker processes, and a keyframe's samples do not depend on the others."""

from __future__ import annotations

import dataclasses
import pickle

import numpy as np
import pytest
from map_synth import FRAME_SIZE, scene, window, write_sequence

from topomap.build import build_map
from topomap.store import load_map, save_map
from topomap.config import BuildConfig, FeatureConfig, LocalizeConfig
from topomap.errors import CalibrationError
from topomap.localize import Localizer
from topomap.parallel import DaskExecutor, InlineExecutor, ProcessExecutor
from topomap.self_supervision import (
    _without_images,
    calibrate_map,
    calibrate_on_queries,
    experience_labels,
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


@pytest.fixture(scope="module")
def two_walks(tmp_path_factory, walk_map):
    """The walk, and the same walk again a little lower and aside appended as a second experience."""
    folder = tmp_path_factory.mktemp("walk2")
    write_sequence(folder, [window(scene(4, width=4000), x + 40.0, y=60.0) for x in XS])
    # the append extends the base's nodes, edges and index in place: a copy read back from a file
    base = load_map(save_map(walk_map, tmp_path_factory.mktemp("walk-copy") / "walk.topomap"))
    m = build_map(folder, CONFIG, base=base)
    assert m.experiences()[1]["links"], "the second walk should be joined to the first by loop closures"
    return m


def _chains(m):
    return [[n for n in sorted(m.nodes) if m.nodes[n].sequence == s] for s in (0, 1)]


@pytest.mark.slow  # its fixture builds and appends a second walk (~15 s)
def test_an_appended_keyframe_is_labelled_where_the_joins_around_it_place_it(two_walks):
    a, b = _chains(two_walks)
    m = dataclasses.replace(two_walks, arrays=dict(two_walks.arrays),
                            edges={k: e for k, e in two_walks.edges.items()
                                   if two_walks.nodes[e.a].sequence == two_walks.nodes[e.b].sequence})
    assert experience_labels(m) == {}  # nothing joins the experiences: nothing is known
    m.set_aligned_links([(b[1], a[2], 1.0), (b[5], a[6], 1.0)])
    labels = experience_labels(m)
    assert labels[b[1]] == (0, tuple(sorted({a[1], a[2], a[3]})))  # the join and its neighbours
    assert labels[a[2]] == (1, tuple(sorted({b[0], b[1], b[2]})))  # both ways
    assert labels[b[3]] == (0, (a[3], a[4], a[5]))  # halfway between the joins, +-1 node
    assert b[0] not in labels and b[6] not in labels  # outside the joined stretch: unknown
    # joins at an impossible pace (4 keyframes of one walk, 10 nodes of the other) label nothing between
    m.set_aligned_links([(b[1], a[0], 1.0), (b[5], a[10], 1.0)])
    assert b[3] not in experience_labels(m)


@pytest.mark.slow  # its fixture builds and appends a second walk (~15 s)
def test_an_appended_experience_calibrates_on_its_own_images(two_walks):
    inline, pooled = fresh(two_walks), fresh(two_walks)
    cal = calibrate_map(inline, queries=12, seed=3)
    ff = cal.fitted_for
    assert ff["experience_samples"] >= 5 and 0 < ff["experience_right"] <= ff["experience_samples"]
    with ProcessExecutor(2) as ex:  # the same calibration from worker processes
        assert calibrate_map(pooled, queries=12, seed=3, executor=ex) == cal


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


def test_a_big_map_is_calibrated_here_not_copied_to_every_worker(walk_map, monkeypatch):
    import topomap.self_supervision as ss

    monkeypatch.setattr(ss, "PARALLEL_MAX_NODES", len(walk_map.nodes) - 1)
    ex = RecordingExecutor()
    cal = calibrate_map(fresh(walk_map), queries=12, seed=3, executor=ex)
    assert ex.shared_bytes == [] and ex.task_bytes == []  # nothing shipped
    assert cal == calibrate_map(fresh(walk_map), queries=12, seed=3)


def test_the_same_calibration_on_dask(walk_map):
    with DaskExecutor(None, 2, processes=False) as ex:
        cal = calibrate_map(fresh(walk_map), queries=12, seed=3, executor=ex)
    assert cal == calibrate_map(fresh(walk_map), queries=12, seed=3)


def _labelled_queries(m, seed: int, n: int):
    """(image, right nodes) of ``n`` views of the walk seen again (noise, a few px aside; right: the
    node of the nearest mapped view or one beside it) and as many of a place not in the map."""
    rng = np.random.default_rng(seed)
    node_of = [f.node for f in m.frames]
    tex, other = scene(4, width=4000), scene(11, width=4000)
    out = []
    for _ in range(n):
        x = rng.uniform(0.0, XS[-1])
        i = int(np.argmin(np.abs(XS - x)))
        img = window(tex, x, zoom=rng.uniform(0.8, 1.25), y=40.0 + rng.uniform(-6, 6))
        img = np.clip(img + rng.normal(0, rng.uniform(5.0, 70.0), FRAME_SIZE[::-1]), 0, 255)
        out.append((img.astype(np.uint8), {node_of[j] for j in range(max(0, i - 1), min(len(XS), i + 2))}))
        out.append((window(other, rng.uniform(0.0, XS[-1]), y=40.0), set()))
    return out


@pytest.mark.slow  # builds one or more maps end to end (~8-30 s)
def test_a_calibration_fitted_on_labelled_queries_matches_their_frequency(walk_map):
    m = fresh(walk_map)
    cal = calibrate_on_queries(m, _labelled_queries(m, 0, 40), seed=1)
    ff = cal.fitted_for
    assert ff["labelled"] and ff["samples"] == 80 and 0 < ff["right"] < 80 and m.meta["calibration"] == cal.to_dict()
    # held-out queries of the same kind: the confidence is their frequency of being right
    loc = Localizer(m)
    assert loc.calibration == cal
    held = [(loc.localize(img), right) for img, right in _labelled_queries(m, 1, 40)]
    conf = np.array([r.confidence for r, _ in held])
    ok = np.array([r.node in right for r, right in held])
    assert abs(conf.mean() - ok.mean()) < 0.1 and conf[ok].mean() > conf[~ok].mean() + 0.5


def test_too_few_or_one_sided_labelled_queries_fit_no_calibration(walk_map):
    m = fresh(walk_map)
    queries = _labelled_queries(m, 0, 40)
    with pytest.raises(CalibrationError, match="need at least 30"):
        calibrate_on_queries(m, queries[:20])
    with pytest.raises(CalibrationError, match="both right and wrong"):
        calibrate_on_queries(m, [q for q in queries if not q[1]])  # all wrong: a place not in the map
    assert "calibration" not in m.meta


def _labelled_walk(m, seed: int, n: int, foreign: int):
    """(image, right nodes) of ``n`` views along the walk in order (noise, a few px aside), then
    ``foreign`` views of a place not in the map: a labelled traversal for the sequence filter."""
    rng = np.random.default_rng(seed)
    node_of = [f.node for f in m.frames]
    tex, other = scene(4, width=4000), scene(11, width=4000)
    out = []
    for x in np.linspace(0.0, XS[-1], n):
        i = int(np.argmin(np.abs(XS - x)))
        img = np.clip(window(tex, x, y=40.0 + rng.uniform(-6, 6)) + rng.normal(0, 8.0, FRAME_SIZE[::-1]), 0, 255)
        out.append((img.astype(np.uint8), {node_of[j] for j in range(max(0, i - 1), min(len(XS), i + 2))}))
    out += [(window(other, x, y=40.0), set()) for x in np.linspace(0.0, XS[-1], foreign)]
    return out


@pytest.mark.slow  # builds one or more maps end to end (~8-30 s)
def test_labelled_queries_in_order_calibrate_the_sequence_confidence_too(walk_map):
    from topomap.localize import SequenceLocalizer, sequence_evidence

    m = fresh(walk_map)
    queries = _labelled_walk(m, 0, 40, 20)
    cal = calibrate_on_queries(m, queries, seed=1)
    assert cal.sequence is not None and cal.fitted_for["sequence_right"] >= 10
    loc = Localizer(m)
    assert loc.calibration.sequence == cal.sequence  # stored in the map's meta, read back
    raw = SequenceLocalizer(Localizer(m, LocalizeConfig(use_calibration=False)))
    filt = SequenceLocalizer(loc)
    for img, _ in queries[:10]:
        r, r0 = filt.update(img), raw.update(img)
        # the same filter; its belief mass on the answer mapped to a probability
        assert r.node == r0.node and r.evidence["belief"] == pytest.approx(r0.confidence)
        evidence = sequence_evidence(r0.confidence, r0.evidence["elsewhere"])
        assert r.calibrated and r.confidence == pytest.approx(cal.sequence.probability(evidence))
    # a place not in the map, walked: the calibrated filter declares none of it
    filt.reset()
    away = [filt.update(window(scene(12, width=4000), x, y=40.0)) for x in np.linspace(0.0, XS[-1], 20)]
    assert not any(r.localized for r in away)


def test_a_sequence_rarely_wrong_keeps_the_filters_posterior(walk_map):
    m = fresh(walk_map)
    queries = _labelled_walk(m, 0, 40, 0)
    queries += [q for q in _labelled_queries(m, 2, 20) if not q[1]]  # foreign views, alone: wrong single frames
    cal = calibrate_on_queries(m, queries[:40] + queries[40:46], seed=1)
    # fewer than MIN_SEQUENCE_EACH wrong answers of the filter: its upper end cannot be calibrated
    assert cal.sequence is None and "sequence" not in m.meta["calibration"]
