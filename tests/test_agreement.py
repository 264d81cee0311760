"""Image agreement with a goal keyframe (topomap.agreement): its own view agrees, another place's does not."""

from __future__ import annotations

import pytest
from conftest import walk_map_file

from topomap.agreement import UNRELATED_THUMBNAIL_SAD, GoalAgreement
from topomap.images import read_image
from topomap.localize import Localizer
from topomap.matching import verify
from topomap.store import load_map


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    """The whole out-and-back walk (its middle node, at the far end, shares no view with node 1): the
    session's one build of it (shared with test_build.py), read back from its file."""
    imgs, path = walk_map_file(tmp_path_factory)
    m = load_map(path)
    return m, imgs, Localizer(m)


def test_the_keyframe_view_agrees_and_a_distant_one_does_not(walk):
    m, imgs, loc = walk
    nodes = sorted(m.nodes)
    goal, far = nodes[1], nodes[len(nodes) // 2]
    agree = GoalAgreement(m, flow_bound=0.02, descriptor_fraction=0.5)

    def check(node_shown, node_goal, **kw):
        q = loc.prepare(read_image(imgs / m.nodes[node_shown].source))
        return agree.agrees(q, verify(q.features, m.nodes[node_goal].features, m.config.match), node_goal, **kw)

    assert check(goal, goal)
    assert not check(far, goal)
    assert not check(nodes[2], goal)  # verifies, but its matches moved more than 2 % of the width
    assert 0 < agree.neighbour_distance(goal) < 2 * UNRELATED_THUMBNAIL_SAD
    away = agree.away_descriptors(goal)
    assert away is not None and len(away) <= len(m.nodes) - 2
