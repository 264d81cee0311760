"""Fixtures of the simulator tests: small hand-made worlds, the default world, one short teach run."""

from __future__ import annotations

import pytest

from topomap.sim.world import default_world


@pytest.fixture(scope="session")
def world():
    return default_world()


@pytest.fixture(scope="session")
def taught(tmp_path_factory, world):
    """A short teach run (route room3 of the default world, ~20 images)."""
    from topomap.sim.teach import teach

    out = tmp_path_factory.mktemp("teach") / "room3"
    return teach(world, "room3", out)


@pytest.fixture(scope="session")
def renderer(world):
    """One PyBullet scene of the default world (320x240) shared by the tests that only need images."""
    from topomap.sim.render import PyBulletRenderer
    from topomap.sim.simulator import default_camera

    r = PyBulletRenderer(world, default_camera())
    yield r
    r.close()
