"""Hand-made worlds for the simulator tests (imported by the test modules of tests/sim)."""

from __future__ import annotations

from topomap.sim.world import Marker, Rect, WaypointRoute, Wall, World


def box_world(half_m: float = 100.0, markers: tuple[Marker, ...] = (), texture: str = "proc:bricks:1") -> World:
    """A square room ``[-half, half]^2`` with its walls facing inwards (counter-clockwise)."""
    h = half_m
    corners = [(-h, -h), (h, -h), (h, h), (-h, h)]
    walls = tuple(Wall(*corners[i], *corners[(i + 1) % 4], texture) for i in range(4))
    return World(
        walls=walls,
        free=(Rect(-h, -h, h, h),),
        routes=(WaypointRoute("across", ((-h / 2, 0.0), (h / 2, 0.0))),),
        markers=markers,
        name="box",
    )
