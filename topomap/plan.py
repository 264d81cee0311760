"""Routes over the map graph: edge costs that say how hard servoing along an edge is, Dijkstra, and
re-planning after an edge failed during navigation (docs/theory.md section 4).

Navigation executes a route as a chain of appearance-servo subtasks toward consecutive node images,
so a route should be cheap to *servo*, not merely short: an edge whose keyframes share few verified
matches, or whose matches move far across the image, is a hard servo (features near the chance
level, large relative motion, points leaving the field of view). :func:`edge_cost` turns the figures
the map stores on each :class:`~topomap.graph.Edge` into a cost in *hops* (one easy edge ~ 1), and
:class:`Planner` runs networkx's Dijkstra on them::

    planner = Planner(tmap)
    route = planner.route(3, 12)        # Route(nodes=[3, 4, ..., 12], edges=[(3, 4), ...], cost, hops)
    planner.penalize(7, 8)              # servoing 7 -> 8 failed: make that edge dearer
    route = planner.route(7, 12)        # avoids (7, 8) when a cheaper alternative exists
    planner.distrust(57, 91)            # routes through loop closure 57-91 failed: use it only if nothing else leads
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import networkx as nx

from topomap.config import BuildConfig, PlanConfig
from topomap.errors import ConfigError, NodeNotFoundError, NoRouteError
from topomap.graph import Edge, EdgeKind, TopoMap

__all__ = ["edge_cost", "Route", "Planner", "DISTRUSTED_COST"]

log = logging.getLogger(__name__)
log.addHandler(logging.NullHandler())

# Added to a distrusted loop closure's cost [hops]: more than any route of verified edges can cost,
# so routes cross the fewest distrusted edges first and only then compare costs.
DISTRUSTED_COST = 1e9


def edge_cost(edge: Edge, map_config: BuildConfig, plan_config: PlanConfig, working_size: tuple[int, int]) -> float:
    """Cost [hops] of servoing along ``edge`` of a map built with ``map_config`` (docs/theory.md section 4).

    ``working_size``: ``(width, height)`` [px] at which the map's keypoints and ``edge.flow_px``
    are expressed (``TopoMap.working_size``). With ``n0 = map_config.match.min_inliers`` (the
    matcher's chance level: fewer verified matches mean "no geometric relation")::

        inliers <  n0:  cost = unverified_cost                                   (a stated constant)
        inliers >= n0:  q    = (inliers - n0) / n0                               margin above chance
                        cost = hop_cost + inlier_weight / (q + inlier_softening)
                             + flow_weight * min(flow_px / diagonal_px, 1)

    So the cost rises steeply as the inliers fall towards ``n0`` (at most ``inlier_weight /
    inlier_softening`` there) and linearly with the median image motion; every verified edge costs
    less than ``unverified_cost`` (checked by :class:`PlanConfig`). Unverified edges (a sequential
    edge whose frames did not verify) stay traversable, as a last resort.
    """
    chance_inliers = map_config.match.min_inliers  # n0
    if edge.inliers < chance_inliers:
        return float(plan_config.unverified_cost)
    width_px, height_px = working_size
    diagonal_px = math.hypot(width_px, height_px)
    if diagonal_px <= 0:
        raise ConfigError(f"working size {width_px}x{height_px} px is empty; the map's camera is damaged")
    flow_px = edge.flow_px
    # A missing or nonsensical motion counts as the worst case, a whole image diagonal.
    flow_fraction = min(max(flow_px, 0.0) / diagonal_px, 1.0) if math.isfinite(flow_px) else 1.0
    margin_q = (edge.inliers - chance_inliers) / chance_inliers
    return (
        plan_config.hop_cost
        + plan_config.inlier_weight / (margin_q + plan_config.inlier_softening)
        + plan_config.flow_weight * flow_fraction
    )


@dataclass(frozen=True)
class Route:
    """A route from ``nodes[0]`` to ``nodes[-1]``.

    ``nodes``: node ids in travel order (one node when start == goal); ``edges``: ``(from, to)``
    pairs in travel order, ``len(nodes) - 1`` of them; ``edge_costs``: the cost [hops] of each
    edge as planned (penalties included); ``cost``: their sum; ``hops``: ``len(edges)``.
    """

    nodes: list[int]
    edges: list[tuple[int, int]]
    cost: float
    hops: int
    edge_costs: list[float] = field(default_factory=list)

    @property
    def start(self) -> int:
        return self.nodes[0]

    @property
    def goal(self) -> int:
        return self.nodes[-1]


class Planner:
    """Shortest servo-cost routes on a :class:`TopoMap`, with penalties for edges that failed.

    The edge costs are computed once, from the map as it is when the planner is made; make a new
    planner after adding nodes or edges. Penalties are planner state: they last until
    :meth:`reset_penalties`.
    """

    def __init__(self, tmap: TopoMap, config: PlanConfig = PlanConfig()) -> None:
        if not isinstance(config, PlanConfig):
            raise ConfigError(f"Planner needs a PlanConfig, got {type(config).__name__}")
        self.map = tmap
        self.config = config
        self._graph = nx.Graph()
        self._graph.add_nodes_from(sorted(tmap.nodes))
        for e in sorted(tmap.edges.values(), key=lambda e: e.key):
            self._graph.add_edge(e.a, e.b, cost=edge_cost(e, tmap.config, config, tmap.working_size),
                                 directed=e.kind is EdgeKind.SEQUENTIAL)
        self._prefer_taught_chains()
        self._penalty: dict[tuple[int, int], float] = {}  # (a, b), a < b -> product of failure factors
        self._distrusted: set[tuple[int, int]] = set()  # (a, b), a < b: loop closures routes avoid if they can

    def _prefer_taught_chains(self) -> None:
        """Short shortcuts along one sequence cost at least the taught chain they skip
        (``PlanConfig.chain_shortcut_max_skip``)."""
        skip = self.config.chain_shortcut_max_skip
        if skip < 2:
            return
        tmap, n0 = self.map, self.map.config.match.min_inliers
        for e in tmap.edges.values():
            if e.kind is EdgeKind.SEQUENTIAL or tmap.nodes[e.a].sequence != tmap.nodes[e.b].sequence:
                continue
            if e.b - e.a > skip:  # node ids follow the build order within a sequence
                continue
            chain = range(e.a, e.b)
            links = [tmap.edge(i, i + 1) for i in chain]
            if all(x is not None and x.kind is EdgeKind.SEQUENTIAL and x.inliers >= n0 for x in links):
                taught = sum(self._graph.edges[i, i + 1]["cost"] for i in chain)
                data = self._graph.edges[e.a, e.b]
                data["cost"] = max(data["cost"], 1.01 * taught)
                data["directed"] = True  # a local shortcut has the taught direction too

    # ------------------------------------------------------------------ costs
    def base_cost(self, a: int, b: int) -> float:
        """The cost [hops] of the edge ``a``-``b`` without penalties."""
        return self._graph.edges[self._edge_key(a, b)]["cost"]

    def cost(self, a: int, b: int) -> float:
        """The cost [hops] of travelling ``a`` -> ``b`` as the planner sees it now (penalties and the
        reverse factor included)."""
        key = self._edge_key(a, b)
        return self._weight(a, b, self._graph.edges[key]) or math.inf

    @property
    def penalties(self) -> dict[tuple[int, int], float]:
        """Current penalty factor of each penalised edge ``(a, b)``, ``a < b``."""
        return dict(self._penalty)

    def penalize(self, a: int, b: int, factor: float | None = None) -> float:
        """Servoing along ``a``-``b`` failed: multiply its cost by ``factor`` (default
        ``config.failure_factor``; repeated failures compound). ``math.inf`` closes the edge.

        Later routes avoid the edge whenever an alternative costs less than the penalised edge.
        Returns the edge's new cost [hops].
        """
        key = self._edge_key(a, b)
        factor = self.config.failure_factor if factor is None else float(factor)
        if math.isnan(factor) or factor < 1:
            raise ConfigError(f"penalty factor {factor} must be at least 1")
        self._penalty[key] = self._penalty.get(key, 1.0) * factor
        log.info("edge %d-%d penalised x%g (cost now %g)", key[0], key[1], self._penalty[key], self.cost(*key))
        return self.cost(*key)

    def reset_penalties(self) -> None:
        """Forget every penalty and distrust: costs are the map's again."""
        self._penalty.clear()
        self._distrusted.clear()

    def against_taught(self, a: int, b: int) -> bool:
        """Whether travelling ``a`` -> ``b`` walks a taught chain backwards (a sequential edge or a
        shortcut along one, ``b`` taught before ``a``): the robot then comes at ``b``'s keyframe from
        the front, with ``b`` behind the view it saw. False for an edge that is not in the graph."""
        return self._graph.has_edge(a, b) and _backwards(a, b, self._graph.edges[self._edge_key(a, b)])

    # ------------------------------------------------------------------ loop closures
    def is_loop_claim(self, a: int, b: int) -> bool:
        """Whether the edge ``a``-``b`` rests on appearance alone: a loop closure between nodes of
        different sequences, or of one sequence more than ``chain_shortcut_max_skip`` steps apart.
        Sequential edges were driven in the teach run, short shortcuts are tied to the taught chain
        they skip, manual edges are the user's word."""
        key = self._edge_key(a, b)
        edge = self.map.edge(*key)
        if edge is None or edge.kind is not EdgeKind.LOOP:
            return False
        na, nb = self.map.nodes[key[0]], self.map.nodes[key[1]]
        return na.sequence != nb.sequence or key[1] - key[0] > self.config.chain_shortcut_max_skip

    def loop_cluster(self, a: int, b: int) -> list[tuple[int, int]]:
        """The loop closures that claim the same revisit as ``a``-``b`` (itself included, sorted):
        the loop-claim edges joining a node within ``chain_shortcut_max_skip`` steps of one end (same
        sequence) to one within as many of the other. A repeated wall makes several such edges; they
        stand or fall together."""
        key = self._edge_key(a, b)
        if not self.is_loop_claim(*key):
            return []
        w = max(self.config.chain_shortcut_max_skip, 1)
        nodes = self.map.nodes

        def close(x: int, y: int) -> bool:
            return nodes[x].sequence == nodes[y].sequence and abs(x - y) <= w

        out = []
        for c, d in self._graph.edges:
            c, d = min(c, d), max(c, d)
            if ((close(c, key[0]) and close(d, key[1])) or (close(c, key[1]) and close(d, key[0]))) \
                    and self.is_loop_claim(c, d):
                out.append((c, d))
        return sorted(out)

    def distrust(self, a: int, b: int) -> list[tuple[int, int]]:
        """Routes that crossed the loop closure ``a``-``b`` kept failing: from now on routes avoid it
        and the loop closures of its :meth:`loop_cluster` whenever any route avoids them, and cross
        as few of them as they can otherwise (an appearance-only claim of one place is the likeliest
        wrong step of a route). Returns the edges distrusted (empty for an edge that is no loop claim)."""
        cluster = self.loop_cluster(a, b)
        self._distrusted.update(cluster)
        if cluster:
            log.info("loop closures %s distrusted", ", ".join(f"{c}-{d}" for c, d in cluster))
        return cluster

    @property
    def distrusted(self) -> list[tuple[int, int]]:
        """The distrusted loop closures ``(a, b)``, ``a < b``, sorted."""
        return sorted(self._distrusted)

    # ------------------------------------------------------------------ routes
    def route(self, start: int, goal: int) -> Route:
        """The cheapest route from ``start`` to ``goal`` (Dijkstra on the current costs).

        Raises :class:`NodeNotFoundError` for an id the map does not contain and
        :class:`NoRouteError` when no path joins the two nodes (different components, or every
        path crosses a closed edge).
        """
        start, goal = self._node_id(start), self._node_id(goal)
        if start == goal:
            return Route(nodes=[start], edges=[], cost=0.0, hops=0, edge_costs=[])
        try:
            cost, nodes = nx.single_source_dijkstra(self._graph, start, goal, weight=self._weight)
        except nx.NetworkXNoPath:
            raise self._no_route(start, goal) from None
        edges = list(zip(nodes[:-1], nodes[1:]))
        return Route(nodes=[int(n) for n in nodes], edges=edges, cost=float(cost), hops=len(edges),
                     edge_costs=[self.cost(a, b) for a, b in edges])

    def costs_from(self, start: int) -> dict[int, float]:
        """Cost of the cheapest route from ``start`` to every node it can reach (one Dijkstra)."""
        lengths = nx.single_source_dijkstra_path_length(self._graph, self._node_id(start), weight=self._weight)
        return {int(n): float(c) for n, c in lengths.items()}

    # ------------------------------------------------------------------ helpers
    def _weight(self, a: int, b: int, data: dict) -> float | None:
        """Cost of travelling a -> b (networkx passes the node being expanded first)."""
        key = (min(a, b), max(a, b))
        w = data["cost"] * self._penalty.get(key, 1.0)
        if _backwards(a, b, data):
            w *= self.config.reverse_factor
        if key in self._distrusted:
            w += DISTRUSTED_COST
        # networkx hides an edge whose weight is None: a closed (infinitely penalised) edge
        return None if math.isinf(w) else w

    def _node_id(self, node_id: int) -> int:
        if isinstance(node_id, bool) or not isinstance(node_id, int):
            try:
                as_int = int(node_id)
            except (TypeError, ValueError):
                as_int = None
            if as_int is None or as_int != node_id:
                raise NodeNotFoundError(f"node id {node_id!r} is not an integer; {self._valid_ids()}")
            node_id = as_int
        if node_id not in self._graph:
            raise NodeNotFoundError(f"node {node_id} is not in this map; {self._valid_ids()}")
        return node_id

    def _valid_ids(self) -> str:
        ids = sorted(self._graph.nodes)
        if not ids:
            return "the map has no nodes"
        if ids[-1] - ids[0] + 1 == len(ids):
            return f"valid ids are {ids[0]}..{ids[-1]}"
        return f"valid ids are {', '.join(map(str, ids[:8]))}{', ...' if len(ids) > 8 else ''} ({len(ids)} nodes)"

    def _edge_key(self, a: int, b: int) -> tuple[int, int]:
        a, b = self._node_id(a), self._node_id(b)
        key = (min(a, b), max(a, b))
        if not self._graph.has_edge(*key):
            raise NoRouteError(f"no edge joins nodes {a} and {b}; only edges of the map can be penalised or costed")
        return key

    def _no_route(self, start: int, goal: int) -> NoRouteError:
        comp_start = nx.node_connected_component(self._graph, start)
        if goal in comp_start:
            closed = sorted(k for k, f in self._penalty.items() if math.isinf(f))
            return NoRouteError(
                f"no route from node {start} to node {goal}: every path crosses a closed edge "
                f"({', '.join(f'{a}-{b}' for a, b in closed)}); reset the planner's penalties or penalise with a finite factor"
            )
        comp_goal = nx.node_connected_component(self._graph, goal)
        parts = len(list(nx.connected_components(self._graph)))
        return NoRouteError(
            f"no route from node {start} to node {goal}: they lie in different parts of the map (node {start} in "
            f"one of {len(comp_start)} nodes, node {goal} in one of {len(comp_goal)}; the map has {parts} parts); "
            f"link them by appending a sequence that passes through both places (topomap build --append)"
        )


def _backwards(a: int, b: int, data: dict) -> bool:
    """Whether ``a`` -> ``b`` along an edge with graph attributes ``data`` walks a taught chain backwards:
    the edge has the taught direction (``directed``) and node ids follow the taught order within a sequence."""
    return bool(data.get("directed")) and b < a
