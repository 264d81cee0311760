"""topomap.plan and ``topomap plan``: servo-cost edge weights, Dijkstra routes, penalties and
re-planning, bad input (unknown node, no route, missing or foreign map)."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from conftest import dataset

from topomap.camera import CameraIntrinsics
from topomap.config import PLAN_PRESETS, BuildConfig, MatchConfig, PlanConfig, plan_preset
from topomap.errors import ConfigError, NodeNotFoundError, NoRouteError, TopomapError
from topomap.features import Features
from topomap.graph import Edge, EdgeKind, Node, TopoMap
from topomap.plan import Planner, Route, edge_cost
from topomap.store import save_map

SIZE = (640, 480)  # working size of the hand-made maps [px]; diagonal 800 px
DIAG = 800.0
CFG = BuildConfig()  # chance level n0 = CFG.match.min_inliers = 15
N0 = CFG.match.min_inliers
STRONG, WEAK = 300, 17  # inliers of an easy and of a hard (near-chance) servo


def make_map(n: int, edges: list[tuple[int, int, int, float]], kind: EdgeKind = EdgeKind.SEQUENTIAL) -> TopoMap:
    """``n`` feature-less nodes and edges ``(a, b, inliers, flow_px)``."""
    m = TopoMap(camera=CameraIntrinsics.default(*SIZE), config=CFG)
    for i in range(n):
        m.add_node(Node(i, 0, i, f"k{i:03d}.png", Features.empty("orb", SIZE), np.zeros((6, 8), np.uint8)))
    for a, b, inliers, flow in edges:
        m.add_edge(Edge(a, b, kind if abs(a - b) == 1 else EdgeKind.LOOP, inliers, min(1.0, inliers / 500), flow))
    return m


def cost(inliers: int, flow_px: float = 0.0, plan: PlanConfig = PlanConfig(), config: BuildConfig = CFG) -> float:
    return edge_cost(Edge(0, 1, EdgeKind.SEQUENTIAL, inliers, 0.1, flow_px), config, plan, SIZE)


# ----------------------------------------------------------------------------- edge costs
def test_more_inliers_is_cheaper_and_steepest_near_chance():
    costs = [cost(n) for n in (N0, N0 + 1, 20, 30, 60, 120, 500, 5000)]
    assert all(a > b for a, b in zip(costs, costs[1:]))
    # the inlier term grows fast towards the chance level, slowly far above it
    assert cost(N0) - cost(2 * N0) > 10 * (cost(8 * N0) - cost(16 * N0))
    assert cost(5000) == pytest.approx(PlanConfig().hop_cost, abs=0.01)


def test_more_motion_is_dearer_and_saturates_at_the_diagonal():
    costs = [cost(100, f) for f in (0.0, 10.0, 100.0, 400.0, DIAG)]
    assert all(a < b for a, b in zip(costs, costs[1:]))
    assert costs[-1] - costs[0] == pytest.approx(PlanConfig().flow_weight)  # one diagonal = flow_weight hops
    assert cost(100, 5 * DIAG) == cost(100, float("nan")) == costs[-1]


def test_formula_as_documented():
    p = PlanConfig()
    q = 1.0  # inliers = 2 n0
    expected = p.hop_cost + p.inlier_weight / (q + p.inlier_softening) + p.flow_weight * 200.0 / DIAG
    assert cost(2 * N0, 200.0) == pytest.approx(expected)


def test_unverified_edge_is_dearest_but_finite():
    p = PlanConfig()
    worst_verified = cost(N0, DIAG)
    for n in (0, 1, N0 - 1):
        assert cost(n, 0.0) == p.unverified_cost > worst_verified
    assert math.isfinite(p.unverified_cost)


def test_chance_level_comes_from_the_map_config():
    strict = BuildConfig(match=MatchConfig(min_inliers=50), keyframe_min_inliers=60, loop_min_inliers=50)
    assert cost(40, config=strict) == PlanConfig().unverified_cost  # below this map's chance level
    assert cost(40) < 3.0  # fine for a map with n0 = 15


def test_hops_preset_counts_servo_subtasks():
    hops = plan_preset("hops")
    assert cost(N0, DIAG, hops) == cost(5000, 0.0, hops) == hops.hop_cost
    assert cost(3, 0.0, hops) == hops.unverified_cost
    assert set(PLAN_PRESETS) >= {"default", "hops"}
    with pytest.raises(ConfigError, match="unknown plan preset 'x'; choose one of: default, hops"):
        plan_preset("x")


@pytest.mark.parametrize("bad, match", [
    (dict(unverified_cost=5.0), "must exceed the dearest verified edge"),
    (dict(failure_factor=0.5), "failure_factor"),
    (dict(hop_cost=0.0), "hop_cost"),
    (dict(inlier_softening=0.0), "inlier_softening"),
    (dict(flow_weight=-1.0), "flow_weight"),
])
def test_bad_plan_config(bad, match):
    with pytest.raises(ConfigError, match=match):
        PlanConfig(**bad)


# ----------------------------------------------------------------------------- routes
def test_strong_chain_beats_a_weak_shortcut():
    # 0-1-2-3 easy servos; 0-3 barely above chance with large motion
    m = make_map(4, [(0, 1, STRONG, 40.0), (1, 2, STRONG, 40.0), (2, 3, STRONG, 40.0), (0, 3, WEAK, 300.0)])
    r = Planner(m).route(0, 3)
    assert r.nodes == [0, 1, 2, 3] and r.hops == 3
    # counting hops only, the shortcut wins
    assert Planner(m, plan_preset("hops")).route(0, 3).nodes == [0, 3]


def test_good_shortcut_beats_a_long_chain():
    # a loop closure with plenty of inliers skips twelve easy servos (more than
    # chain_shortcut_max_skip taught steps: a real loop closure, not a local shortcut)
    m = make_map(13, [(i, i + 1, STRONG, 40.0) for i in range(12)] + [(0, 12, 80, 120.0)])
    r = Planner(m).route(0, 12)
    assert r.nodes == [0, 12] and r.edges == [(0, 12)] and r.hops == 1


def test_route_fields_are_consistent():
    m = make_map(5, [(0, 1, 100, 50.0), (1, 2, 60, 150.0), (2, 3, 200, 10.0), (3, 4, 30, 0.0)])
    p = Planner(m)
    r = p.route(4, 0)  # travel order, against the edge orientation
    assert isinstance(r, Route)
    assert r.nodes == [4, 3, 2, 1, 0] and r.edges == [(4, 3), (3, 2), (2, 1), (1, 0)]
    assert (r.start, r.goal, r.hops) == (4, 0, 4)
    assert r.edge_costs == [p.cost(a, b) for a, b in r.edges] and r.cost == pytest.approx(sum(r.edge_costs))
    # travelled 4 -> 3, against the taught order: the reverse factor applies
    assert r.edge_costs[0] == pytest.approx(p.config.reverse_factor * edge_cost(m.edge(3, 4), m.config, p.config, m.working_size))
    with pytest.raises(dataclasses.FrozenInstanceError):
        r.cost = 0.0


def test_start_equals_goal_is_a_one_node_route():
    r = Planner(make_map(3, [(0, 1, 100, 0.0)])).route(2, 2)  # even an isolated node
    assert (r.nodes, r.edges, r.cost, r.hops) == ([2], [], 0.0, 0)


def test_unverified_edge_only_as_a_last_resort():
    # castle-like: the sequential edge 2-3 did not verify; a verified detour via 4 exists
    m = make_map(5, [(0, 1, 100, 50.0), (1, 2, 100, 50.0), (2, 3, 0, 0.0), (2, 4, N0, 700.0), (3, 4, N0, 700.0)])
    p = Planner(m)
    assert p.route(0, 3).nodes == [0, 1, 2, 4, 3]
    del m.edges[(2, 4)]  # without the detour the unverified edge is still traversable
    r = Planner(m).route(0, 3)
    assert r.nodes == [0, 1, 2, 3] and r.cost >= PlanConfig().unverified_cost


def test_ties_are_broken_the_same_way_every_time():
    m = make_map(4, [(0, 1, 100, 50.0), (1, 3, 100, 50.0), (0, 2, 100, 50.0), (2, 3, 100, 50.0)])
    routes = {tuple(Planner(m).route(0, 3).nodes) for _ in range(5)}
    assert len(routes) == 1 and routes.pop() in {(0, 1, 3), (0, 2, 3)}


# ----------------------------------------------------------------------------- penalties
@pytest.fixture
def square():
    """0-1-2 direct (cheap) and 0-3-4-2 around (dearer)."""
    return make_map(5, [(0, 1, 200, 50.0), (1, 2, 200, 50.0), (0, 3, 150, 80.0), (3, 4, 150, 80.0), (2, 4, 150, 80.0)])


def test_costs_from_agree_with_routes(square):
    p = Planner(square)
    p.penalize(1, 2)
    costs = p.costs_from(0)
    assert costs[0] == 0.0 and set(costs) == set(square.nodes)
    for n in square.nodes:
        assert costs[n] == pytest.approx(p.route(0, n).cost)
    split = make_map(4, [(0, 1, 200, 50.0), (2, 3, 200, 50.0)])
    assert set(Planner(split).costs_from(0)) == {0, 1}  # only what it can reach


def test_penalize_then_replan_takes_the_alternative(square):
    p = Planner(square)
    first = p.route(0, 2)
    assert first.nodes == [0, 1, 2]
    base = p.cost(1, 2)
    assert p.penalize(2, 1) == pytest.approx(base * p.config.failure_factor)  # either orientation
    assert p.penalties == {(1, 2): p.config.failure_factor}
    again = p.route(0, 2)
    assert again.nodes == [0, 3, 4, 2] and again.cost > first.cost
    assert p.route(1, 2).nodes == [1, 2]  # from 1, one failure does not outweigh a four-hop detour ...
    p.penalize(1, 2)
    assert p.route(1, 2).nodes == [1, 0, 3, 4, 2]  # ... a second one does
    bridge = make_map(3, [(0, 1, 200, 50.0), (1, 2, 200, 50.0)])
    q = Planner(bridge)
    q.penalize(1, 2)
    assert q.route(0, 2).nodes == [0, 1, 2]  # no alternative: the failed edge is tried again
    p.reset_penalties()
    assert p.route(0, 2) == first and p.penalties == {} and p.cost(1, 2) == base == p.base_cost(1, 2)


def test_penalties_compound_and_inf_closes_an_edge(square):
    p = Planner(square)
    p.penalize(0, 1, factor=2.0)
    p.penalize(0, 1, factor=3.0)
    assert p.cost(0, 1) == pytest.approx(6.0 * p.base_cost(0, 1))
    p.penalize(1, 2, factor=math.inf)
    assert p.route(1, 2).nodes == [1, 0, 3, 4, 2]
    for e in ((0, 3), (3, 4), (2, 4)):
        p.penalize(*e, factor=math.inf)
    with pytest.raises(NoRouteError, match=r"no route from node 0 to node 2: every path crosses a closed edge"):
        p.route(0, 2)


def test_bad_penalties(square):
    p = Planner(square)
    with pytest.raises(ConfigError, match="at least 1"):
        p.penalize(0, 1, factor=0.5)
    with pytest.raises(NoRouteError, match="no edge joins nodes 0 and 2"):
        p.penalize(0, 2)
    with pytest.raises(NodeNotFoundError, match="node 9 is not in this map"):
        p.penalize(0, 9)
    assert p.penalties == {}


# ----------------------------------------------------------------------------- errors
def test_unknown_node_names_the_valid_range(square):
    p = Planner(square)
    for bad in (7, -1):
        with pytest.raises(NodeNotFoundError, match=rf"node {bad} is not in this map; valid ids are 0\.\.4") as ei:
            p.route(0, bad)
        assert isinstance(ei.value, TopomapError)
    with pytest.raises(NodeNotFoundError, match="not an integer"):
        p.route("two", 0)
    with pytest.raises(NodeNotFoundError, match="not an integer"):
        p.route(1.5, 0)
    assert p.route(np.int64(0), 2.0).nodes == [0, 1, 2]  # integral values of other types are fine


def test_no_route_names_both_nodes_and_their_parts():
    m = make_map(6, [(0, 1, 100, 0.0), (1, 2, 100, 0.0), (3, 4, 100, 0.0)])  # parts {0,1,2} {3,4} {5}
    with pytest.raises(NoRouteError) as ei:
        Planner(m).route(0, 4)
    msg = str(ei.value)
    assert "node 0 to node 4" in msg and "one of 3 nodes" in msg and "one of 2" in msg and "3 parts" in msg
    assert "\n" not in msg and "--append" in msg
    with pytest.raises(NoRouteError, match="node 5 in one of 1"):
        Planner(m).route(1, 5)


def test_planner_wants_a_plan_config(square):
    with pytest.raises(ConfigError, match="PlanConfig"):
        Planner(square, CFG)


# ----------------------------------------------------------------------------- real data
@pytest.mark.slow
def test_castle_avoids_its_unverified_edge():
    from topomap.build import build_map
    from topomap.camera import load_camera

    root = dataset("castle-p30")
    m = build_map(root / "images", camera=load_camera(root / "K.txt"))
    weak = [e for e in m.edges.values() if e.inliers < m.config.match.min_inliers]
    assert weak  # the sequential edge 0028.jpg-0029.jpg does not verify
    p = Planner(m)
    for e in weak:
        r = p.route(e.a, e.b)
        assert r.hops >= 2 and r.cost < PlanConfig().unverified_cost
        assert all(m.edge(a, b).inliers >= m.config.match.min_inliers for a, b in r.edges)


# ----------------------------------------------------------------------------- CLI
@pytest.fixture(scope="module")
def maps(tmp_path_factory):
    """A connected map (the square) and one in two parts, saved with the store."""
    root = tmp_path_factory.mktemp("plan")
    square = make_map(5, [(0, 1, 200, 50.0), (1, 2, 200, 50.0), (0, 3, 150, 80.0), (3, 4, 150, 80.0), (2, 4, 150, 80.0)])
    split = make_map(4, [(0, 1, 100, 10.0), (2, 3, 100, 10.0)])
    return save_map(square, root / "square.topomap"), save_map(split, root / "split.topomap")


def test_cli_json(runner, cli_app, maps):
    res = runner.invoke(cli_app, ["plan", str(maps[0]), "--from", "0", "--to", "2", "--json"])
    assert res.exit_code == 0, res.output
    data = json.loads(res.stdout)
    assert {"route", "cost", "hops", "edges"} <= set(data)
    assert data["route"] == [0, 1, 2] and data["hops"] == 2 and data["keyframes"] == ["k000.png", "k001.png", "k002.png"]
    assert [(e["source"], e["target"], e["kind"], e["inliers"]) for e in data["edges"]] == [
        (0, 1, "sequential", 200), (1, 2, "sequential", 200)]
    assert data["cost"] == pytest.approx(sum(e["cost"] for e in data["edges"]), abs=1e-3)


def test_cli_penalize_replans(runner, cli_app, maps):
    res = runner.invoke(cli_app, ["plan", str(maps[0]), "--from", "0", "--to", "2", "--penalize", "1-2", "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["route"] == [0, 3, 4, 2]


def test_cli_text(runner, cli_app, maps):
    res = runner.invoke(cli_app, ["plan", str(maps[0]), "--from", "4", "--to", "0"])
    assert res.exit_code == 0, res.output
    assert "k004.png" in res.stdout and "k000.png" in res.stdout and "2 hops, total cost" in res.stdout


@pytest.mark.parametrize("args, message", [
    (["{split}", "--from", "0", "--to", "3"], "no route from node 0 to node 3"),
    (["{square}", "--from", "0", "--to", "42"], "node 42 is not in this map; valid ids are 0..4"),
    (["{missing}", "--from", "0", "--to", "1"], "does not exist"),
    (["{foreign}", "--from", "0", "--to", "1"], "is not a topomap map"),
    (["{square}", "--from", "0"], "Missing option '--to'"),
    (["{square}", "--from", "0", "--to", "x"], "Invalid value for '--to'"),
    (["{square}", "--from", "0", "--to", "1", "--penalize", "0-2"], "no edge joins nodes 0 and 2"),
    (["{square}", "--from", "0", "--to", "1", "--penalize", "zero"], "--penalize expects an edge as A-B"),
    (["{square}", "--from", "0", "--to", "1", "--preset", "fastest"], "unknown plan preset 'fastest'"),
])
def test_cli_bad_input_is_one_line(runner, cli_app, maps, tmp_path, args, message):
    foreign = tmp_path / "notes.topomap"
    foreign.write_text("not a map\n")
    paths = {"square": maps[0], "split": maps[1], "missing": tmp_path / "none.topomap", "foreign": foreign}
    res = runner.invoke(cli_app, ["plan"] + [a.format(**paths) for a in args])
    assert res.exit_code == 1
    assert res.exception is None or isinstance(res.exception, SystemExit)  # no traceback
    err = res.stderr.strip()
    assert err.startswith("Error: ") and len(err.splitlines()) == 1 and message in err, err


def test_short_shortcut_along_a_sequence_follows_the_taught_chain():
    # a well-verified proximity edge 0-3 inside one sequence is cheaper by hops, but the taught chain
    # is where servoing is known to work: the planner takes it (chain_shortcut_max_skip)
    m = make_map(6, [(i, i + 1, STRONG, 40.0) for i in range(5)] + [(0, 3, 60, 120.0)])
    assert Planner(m).route(0, 3).nodes == [0, 1, 2, 3]
    assert Planner(m, PlanConfig(chain_shortcut_max_skip=0)).route(0, 3).nodes == [0, 3]
    # penalising the chain makes the shortcut the better route again
    p = Planner(m)
    p.penalize(1, 2)
    assert p.route(0, 3).nodes == [0, 3]


def test_routes_follow_the_taught_direction_when_they_can():
    # a loop 0-1-...-11-0 taught in increasing order (11-0 a loop closure): from 6 back to 4 is two
    # hops against the taught direction, forward around the loop ten; reversing costs
    # reverse_factor times more
    edges = [(i, i + 1, STRONG, 40.0) for i in range(11)]
    m = make_map(12, edges + [(0, 11, STRONG, 40.0)])
    p = Planner(m)
    assert p.cost(1, 2) < p.cost(2, 1) == pytest.approx(PlanConfig().reverse_factor * p.cost(1, 2))
    assert p.route(6, 4).nodes == [6, 5, 4]  # 2 x 3 hops is still cheaper than ten hops forward
    forward = [6, 7, 8, 9, 10, 11, 0, 1, 2, 3, 4]
    assert Planner(m, PlanConfig(reverse_factor=20.0)).route(6, 4).nodes == forward
    # a dead end can only be left backwards
    assert Planner(make_map(3, edges[:2]), PlanConfig(reverse_factor=20.0)).route(2, 0).nodes == [2, 1, 0]


def test_local_shortcuts_carry_the_taught_direction():
    # backwards, a local shortcut must not be cheaper than the reversed chain it skips
    m = make_map(12, [(i, i + 1, STRONG, 40.0) for i in range(11)] + [(5, 8, STRONG, 40.0)])
    p = Planner(m)
    assert p.cost(8, 5) == pytest.approx(p.config.reverse_factor * p.cost(5, 8))
    assert p.route(9, 4).nodes == [9, 8, 7, 6, 5, 4]


def test_against_taught_is_a_taught_chain_walked_backwards():
    p = Planner(twin_walls())
    assert p.against_taught(5, 4) and not p.against_taught(4, 5)  # a sequential edge
    assert p.against_taught(13, 10) and not p.against_taught(10, 13)  # a shortcut along the chain
    assert not p.against_taught(25, 5) and not p.against_taught(5, 25)  # a loop closure has no direction
    assert not p.against_taught(29, 0) and not p.against_taught(3, 1)  # a manual edge; no edge at all


# ----------------------------------------------------------------------------- distrusted loop closures
def twin_walls() -> TopoMap:
    """One sequence 0..29 driven around; loop closures 5-25 and 6-26 (a pair claiming one revisit),
    a short shortcut 10-13 and a manual edge 0-29."""
    edges = [(i, i + 1, STRONG, 0.0) for i in range(29)] + [(5, 25, STRONG, 0.0), (6, 26, STRONG, 0.0), (10, 13, STRONG, 0.0)]
    m = make_map(30, edges)
    m.add_edge(Edge(0, 29, EdgeKind.MANUAL, STRONG, 0.6, 0.0))
    return m


def test_loop_claims_are_long_loop_closures_only():
    p = Planner(twin_walls())
    assert p.is_loop_claim(5, 25) and p.is_loop_claim(26, 6)
    assert not p.is_loop_claim(4, 5)  # driven in the teach run
    assert not p.is_loop_claim(10, 13)  # tied to the taught chain it skips
    assert not p.is_loop_claim(0, 29)  # the user's word
    assert p.loop_cluster(25, 5) == p.loop_cluster(6, 26) == [(5, 25), (6, 26)]
    assert p.loop_cluster(10, 13) == []


def test_a_distrusted_loop_closure_is_crossed_only_where_nothing_else_leads():
    p = Planner(twin_walls())
    assert p.route(4, 24).nodes == [4, 5, 25, 24]
    assert p.distrust(5, 25) == [(5, 25), (6, 26)]  # its twin falls with it
    assert p.distrusted == [(5, 25), (6, 26)]
    detour = p.route(4, 24)
    assert not {(5, 25), (6, 26)} & {(min(e), max(e)) for e in detour.edges}
    assert math.isfinite(detour.cost) and detour.cost < 1e6
    # the only way into a dead end stays open: one distrusted edge rather than none
    m = twin_walls()
    m.add_node(Node(30, 1, 0, "other/k000.png", Features.empty("orb", SIZE), np.zeros((6, 8), np.uint8)))
    m.add_edge(Edge(12, 30, EdgeKind.LOOP, STRONG, 0.6, 0.0))
    q = Planner(m)
    assert q.is_loop_claim(12, 30) and q.distrust(30, 12) == [(12, 30)]
    assert q.route(0, 30).nodes[-2:] == [12, 30]
    q.reset_penalties()
    assert q.distrusted == [] and q.route(4, 24).nodes == [4, 5, 25, 24]
    assert Planner(twin_walls()).distrust(10, 13) == []  # not a loop claim: nothing to distrust
