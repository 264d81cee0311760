"""A map remembers its teach world (meta ``teach_world``); ``topomap navigate`` takes the world options
of ``topomap sim teach`` (``--world``, ``--textures``, ``--conditions``) and needs none of them."""

from __future__ import annotations

import json
import shutil

import pytest

from topomap.build import TEACH_WORLD_KEY, build_map, teach_world_record
from topomap.camera import load_camera
from topomap.sim.conditions import CONDITION_PRESETS
from topomap.sim.world import World, default_world, load_world
from topomap.store import load_map, save_map


@pytest.fixture(scope="module")
def small_map(tmp_path_factory):
    """A short teach run (route room3 of the default world) under ``lighting``, and its map."""
    from topomap.sim.teach import teach

    root = tmp_path_factory.mktemp("small")
    run = teach(default_world(), "room3", root / "teach", conditions="lighting", spacing_m=0.4)
    tmap = build_map(root / "teach", camera=load_camera(run.camera_path))
    return save_map(tmap, root / "map.topomap")


def test_the_map_remembers_the_teach_world_and_its_conditions(small_map):
    m = load_map(small_map)
    taught = m.meta[TEACH_WORLD_KEY]
    folder = small_map.parent / "teach"
    assert taught["world"] == json.loads((folder / "world.json").read_text())
    assert World.from_dict(taught["world"]) == load_world(folder / "world.json")
    assert taught["route"] == "room3" and taught["vehicle"] == "unicycle"
    assert taught["conditions"]["name"] == "lighting"
    assert taught["source"] == str(folder.resolve())


@pytest.mark.slow  # builds one or more maps end to end (~8-30 s)
def test_a_damaged_or_missing_world_file_is_skipped_and_appending_keeps_the_first(small_map, tmp_path, caplog):
    folder = tmp_path / "teach"
    shutil.copytree(small_map.parent / "teach", folder)
    (folder / "world.json").write_text("{oops")
    assert teach_world_record(folder) is None
    assert "unreadable" in caplog.text
    (folder / "world.json").unlink()
    assert teach_world_record(folder) is None
    assert teach_world_record(folder / "0000.png") is None  # not a folder
    m = load_map(small_map)
    first = m.meta[TEACH_WORLD_KEY]
    other = tmp_path / "other"
    shutil.copytree(small_map.parent / "teach", other)
    w = json.loads((other / "world.json").read_text())
    w["name"] = "elsewhere"
    (other / "world.json").write_text(json.dumps(w))
    grown = build_map(other, base=m)
    assert grown.meta[TEACH_WORLD_KEY] == first and "another world" in caplog.text


def _invoke(runner, cli_app, *args):
    return runner.invoke(cli_app, ["navigate", *[str(a) for a in args]])


@pytest.mark.slow
def test_navigate_needs_nothing_but_the_map_and_the_goal(runner, cli_app, small_map, tmp_path):
    """The teach folder lost its world.json: the map's own record of the world is used."""
    m = load_map(small_map)
    (small_map.parent / "teach" / "world.json").rename(tmp_path / "world.json.bak")
    try:
        ids = sorted(m.nodes)
        res = _invoke(runner, cli_app, small_map, "--goal", ids[3], "--start-node", ids[1], "--json")
    finally:
        (tmp_path / "world.json.bak").rename(small_map.parent / "teach" / "world.json")
    assert res.exit_code == 0, res.output
    data = json.loads(res.stdout)
    assert data["success"] and data["final_position_error_m"] < 0.25


def test_world_and_conditions_resolution(small_map, tmp_path):
    from topomap_cli.navigate import _teach_world

    m = load_map(small_map)
    teach_dir = small_map.parent / "teach"
    w, c = _teach_world(m, None, None, teach_dir)
    assert w == World.from_dict(m.meta[TEACH_WORLD_KEY]["world"]) and c == CONDITION_PRESETS["lighting"]
    w7, _ = _teach_world(m, "7", None, teach_dir)
    assert w7.seed == 7
    office, _ = _teach_world(m, "office:3", None, teach_dir)
    assert office.name == "office3"
    old = load_map(small_map)
    old.meta.pop(TEACH_WORLD_KEY)  # a map built before the key: world.json beside its images
    w_old, c_old = _teach_world(old, None, None, teach_dir)
    assert w_old == w and c_old.is_nominal


@pytest.mark.parametrize("args, message", [
    (["--goal", "1", "--textures", "{tmp}/nowhere"], "texture folder"),
    (["--goal", "1", "--conditions", "dusk"], "unknown conditions preset 'dusk'; choose one of: evening, lighting"),
    (["--goal", "1", "--conditions", "lighting,glare=2"], "unknown conditions setting 'glare'"),
    (["--goal", "1", "--world", "office:x"], "must be an integer"),
])
def test_bad_world_options_are_one_line_and_exit_1(runner, cli_app, small_map, tmp_path, args, message):
    res = _invoke(runner, cli_app, small_map, *[a.replace("{tmp}", str(tmp_path)) for a in args])
    assert res.exit_code == 1, res.output
    err = res.stderr.strip()
    assert len(err.splitlines()) == 1 and err.startswith("Error:") and message in err, err


def test_world_options_without_a_map_are_refused(runner, cli_app):
    res = runner.invoke(cli_app, ["navigate", "--conditions", "lighting"])
    assert res.exit_code == 1 and "need a MAP" in res.output


def test_sim_teach_and_render_take_conditions(runner, cli_app, tmp_path):
    import cv2

    for c in ("none", "evening"):
        res = runner.invoke(cli_app, ["sim", "render", "default", "-o", str(tmp_path / f"{c}.png"), "--conditions", c])
        assert res.exit_code == 0, res.output
    assert cv2.imread(str(tmp_path / "evening.png")).mean() < 0.8 * cv2.imread(str(tmp_path / "none.png")).mean()
    res = runner.invoke(cli_app, ["sim", "teach", "-o", str(tmp_path / "t"), "--conditions", "dusk"])
    assert res.exit_code == 1 and "unknown conditions preset 'dusk'" in res.stderr
