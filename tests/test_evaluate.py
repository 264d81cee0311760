"""topomap.evaluate: precision-recall curve, AUC, recall at 100 % precision and Recall@N on hand-made
cases whose answers are worked out in the comments."""

from __future__ import annotations

import numpy as np
import pytest

from topomap.camera import CameraIntrinsics
from topomap.errors import DatasetError
from topomap.evaluate import evaluate, plot_pr, pr_curve
from topomap.features import Features
from topomap.graph import FrameRecord, Node, TopoMap
from topomap.groundtruth import GroundTruth
from topomap.localize import Candidate, Localization, LocalizationStatus


def tiny_map(frames_per_node: int = 2, nodes: int = 10) -> TopoMap:
    """Nodes 0..nodes-1; node i represents frames r{2i}.png and r{2i+1}.png (no features needed)."""
    m = TopoMap(camera=CameraIntrinsics.default(64, 48))
    for i in range(nodes):
        m.add_node(Node(i, 0, i * frames_per_node, f"r{i * frames_per_node}.png", Features.empty("orb", (64, 48)),
                        np.zeros((4, 4), np.uint8)))
        for j in range(frames_per_node):
            k = i * frames_per_node + j
            m.frames.append(FrameRecord(k, 0, k, f"r{k}.png", i))
    return m


def loc(ranking: list[int], confidence: float) -> Localization:
    """A localization answering ``ranking[0]`` with the given ranking of candidates."""
    cands = tuple(Candidate(n, float(-i), -1, 0.0) for i, n in enumerate(ranking))
    status = LocalizationStatus.LOCALIZED if confidence >= 0.5 else LocalizationStatus.UNKNOWN
    return Localization(ranking[0], confidence, status, 0, cands)


# ----------------------------------------------------------------------------- pr_curve
def test_pr_curve_by_hand():
    # sorted by confidence: T F T F, 4 queries with a true match
    # accepted 1: P 1   R .25 | 2: P .5 R .25 | 3: P 2/3 R .5 | 4: P .5 R .5
    p, r, t = pr_curve(np.array([0.6, 0.9, 0.7, 0.8]), np.array([False, True, True, False]), 4)
    np.testing.assert_allclose(p, [1.0, 1.0, 0.5, 2 / 3, 0.5])
    np.testing.assert_allclose(r, [0.0, 0.25, 0.25, 0.5, 0.5])
    np.testing.assert_allclose(t, [np.inf, 0.9, 0.8, 0.7, 0.6])


def test_pr_curve_ties_are_one_threshold():
    # two answers tie at 0.9 (one right, one wrong): no threshold accepts only the right one, so
    # the curve must not show precision 1 at recall 1/3 whichever order the ties come in
    for correct in ([True, False, True], [False, True, True]):
        p, r, t = pr_curve(np.array([0.9, 0.9, 0.5]), np.array(correct), 3)
        np.testing.assert_allclose(p, [1.0, 0.5, 2 / 3])
        np.testing.assert_allclose(r, [0.0, 1 / 3, 2 / 3])
        np.testing.assert_allclose(t, [np.inf, 0.9, 0.5])


def test_pr_curve_without_positives_or_queries():
    for conf, ok, pos in ((np.array([0.9, 0.1]), np.array([False, False]), 0), (np.zeros(0), np.zeros(0, bool), 3)):
        p, r, t = pr_curve(conf, ok, pos)
        assert p.tolist() == [1.0] and r.tolist() == [0.0] and t.tolist() == [np.inf]


# ----------------------------------------------------------------------------- evaluate
def test_evaluate_auc_and_recall_at_full_precision_by_hand():
    m = tiny_map()
    truth = GroundTruth({f"q{i}.png": frozenset({f"r{2 * i}.png"}) for i in range(4)})  # q_i is at node i
    results = [
        ("q0.png", loc([0, 5], 0.9)),  # right, most confident
        ("q1.png", loc([7, 1], 0.8)),  # wrong; right at rank 2
        ("q2.png", loc([2], 0.7)),  # right
        ("q3.png", loc([9, 8, 7, 6, 5, 4, 3], 0.6)),  # wrong; right at rank 7
    ]
    res = evaluate(results, truth, m)
    assert res.queries == res.queries_with_match == 4
    assert res.recall_at == {1: 0.5, 5: 0.75, 10: 1.0}
    # curve (0,1) (.25,1) (.25,.5) (.5,2/3) (.5,.5): area .25 + .25 * (.5 + 2/3) / 2
    assert res.auc == pytest.approx(0.25 + 0.25 * (0.5 + 2 / 3) / 2)
    assert res.recall_at_100_precision == pytest.approx(0.25)
    assert [o.first_correct_rank for o in res.outcomes] == [1, 2, 1, 7]
    assert [o.correct for o in res.outcomes] == [True, False, True, False]
    d = res.to_dict(per_query=True)
    assert d["recall_at_1"] == 0.5 and d["recall_at_10"] == 1.0 and len(d["per_query"]) == 4
    assert d["per_query"][1]["node"] == 7 and d["per_query"][1]["status"] == "localized"


def test_a_node_counts_when_it_represents_any_matching_frame():
    m = tiny_map()
    # q matches frame r3.png, represented by node 1 (frames r2, r3); node 2 is not right
    truth = GroundTruth({"q.png": frozenset({"r3.png"})})
    assert evaluate([("q.png", loc([1], 0.9))], truth, m).recall_at[1] == 1.0
    assert evaluate([("q.png", loc([2, 1], 0.9))], truth, m).recall_at == {1: 0.0, 5: 1.0, 10: 1.0}


def test_a_node_of_another_experience_counts_when_aligned_to_a_right_node():
    m = tiny_map()
    m.add_node(Node(10, 1, 20, "w0.png", Features.empty("orb", (64, 48)), np.zeros((4, 4), np.uint8)))
    m.add_node(Node(11, 1, 21, "w1.png", Features.empty("orb", (64, 48)), np.zeros((4, 4), np.uint8)))
    truth = GroundTruth({"q.png": frozenset({"r3.png"})})  # node 1's frame; the winter run is not in it
    assert evaluate([("q.png", loc([10, 1], 0.9))], truth, m).recall_at[1] == 0.0
    m.set_aligned_links([(10, 1, 0.97)])  # node 10 shows node 1's place; node 11 shows none of the truth
    assert evaluate([("q.png", loc([10, 1], 0.9))], truth, m).recall_at[1] == 1.0
    assert evaluate([("q.png", loc([11, 1], 0.9))], truth, m).recall_at == {1: 0.0, 5: 1.0, 10: 1.0}


def test_queries_without_a_true_match():
    m = tiny_map()
    truth = GroundTruth({"a.png": frozenset({"r0.png"}), "b.png": frozenset(), "c.png": frozenset({"r4.png"})})
    # b has no place in the map: answering it confidently costs precision, not recall
    res = evaluate([("b.png", loc([3], 0.95)), ("a.png", loc([0], 0.9)), ("c.png", loc([2], 0.2))], truth, m)
    assert res.queries == 3 and res.queries_with_match == 2
    assert res.recall_at[1] == 1.0  # both queries with a match are right
    np.testing.assert_allclose(res.precision, [1.0, 0.0, 0.5, 2 / 3])
    np.testing.assert_allclose(res.recall, [0.0, 0.0, 0.5, 1.0])
    assert res.recall_at_100_precision == 0.0  # the most confident answer is wrong
    assert res.auc == pytest.approx(0.5 * (0.0 + 0.5) / 2 + 0.5 * (0.5 + 2 / 3) / 2)
    # a query the ground truth does not name has no match either
    res = evaluate([("a.png", loc([0], 0.9)), ("zzz.png", loc([1], 0.8))], truth, m)
    assert res.queries_with_match == 1 and res.outcomes[1].has_match is False


def test_no_positives_at_all():
    m = tiny_map()
    truth = GroundTruth({"a.png": frozenset(), "b.png": frozenset()})
    res = evaluate([("a.png", loc([0], 0.9)), ("b.png", loc([1], 0.1))], truth, m)
    assert res.queries_with_match == 0 and res.recall_at == {1: 0.0, 5: 0.0, 10: 0.0}
    assert res.auc == 0.0 and res.recall_at_100_precision == 0.0


def test_ground_truth_naming_no_query_is_an_error():
    truth = GroundTruth({"other.png": frozenset({"r0.png"})})
    with pytest.raises(DatasetError, match="names none of the queries.*q1.png"):
        evaluate([("q1.png", loc([0], 0.9)), ("q2.png", loc([1], 0.9))], truth, tiny_map())


def test_plot_pr_writes_a_png(tmp_path):
    truth = GroundTruth({f"q{i}.png": frozenset({f"r{2 * i}.png"}) for i in range(3)})
    res = evaluate([(f"q{i}.png", loc([i if i != 1 else 4], 0.9 - 0.1 * i)) for i in range(3)], truth, tiny_map())
    out = plot_pr(res, tmp_path / "pr.png")
    assert out == tmp_path / "pr.png" and out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 5000
