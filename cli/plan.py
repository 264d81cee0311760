"""``topomap plan``: the cheapest route between two nodes of a map (servo cost, docs/theory.md section 4)."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.table import Table

from topomap.config import PLAN_PRESETS, plan_preset
from topomap.plan import Planner
from topomap.store import load_map
from topomap_cli.app import app, console, fail, print_json


def _edge_pair(text: str) -> tuple[int, int]:
    parts = text.replace(",", "-").split("-")
    if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
        fail(f"--penalize expects an edge as A-B (two node ids), got {text!r}")
    return int(parts[0]), int(parts[1])


@app.command()
def plan(
    map_path: Path = typer.Argument(..., metavar="MAP", help="Map file."),
    start: int = typer.Option(..., "--from", help="Start node id."),
    goal: int = typer.Option(..., "--to", help="Goal node id."),
    preset: str = typer.Option("default", "--preset", help=f"Edge costs: {', '.join(PLAN_PRESETS)}."),
    penalize: list[str] = typer.Option(
        [], "--penalize", metavar="A-B", help="Treat edge A-B as failed once (its cost x the failure factor); repeatable."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON: route, cost, hops, edges."),
) -> None:
    """Plan the route that is easiest to servo along from node --from to node --to."""
    config = plan_preset(preset)
    pairs = [_edge_pair(p) for p in penalize]
    m = load_map(map_path)
    planner = Planner(m, config)
    for a, b in pairs:
        planner.penalize(a, b)
    route = planner.route(start, goal)
    edges = []
    for (a, b), cost in zip(route.edges, route.edge_costs):
        e = m.edge(a, b)
        edges.append({"source": a, "target": b, "kind": e.kind.value, "inliers": e.inliers,
                      "flow_px": round(e.flow_px, 1), "cost": round(cost, 4)})
    keyframes = [m.nodes[n].source for n in route.nodes]
    if as_json:
        print_json({"route": route.nodes, "cost": round(route.cost, 4), "hops": route.hops, "edges": edges,
                    "keyframes": keyframes})
        return
    title = f"{map_path.name}: node {route.start} -> node {route.goal}"
    t = Table(title=title, title_justify="left", box=None, padding=(0, 2))
    for col in ("node", "keyframe", "via edge", "inliers", "flow px", "cost"):
        t.add_column(col, justify="right" if col in ("node", "inliers", "flow px", "cost") else "left")
    t.add_row(str(route.nodes[0]), keyframes[0], "start", "", "", "")
    for n, name, e in zip(route.nodes[1:], keyframes[1:], edges):
        t.add_row(str(n), name, e["kind"], str(e["inliers"]), f"{e['flow_px']:.0f}", f"{e['cost']:.2f}")
    console.print(t)
    console.print(f"{route.hops} hop{'s' if route.hops != 1 else ''}, total cost {route.cost:.2f}")
