"""``topomap sim ...`` through typer's CliRunner: teach, show-world, make-world, render, bad input."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from topomap.camera import load_camera
from topomap.sim.world import load_world


def _ok(result):
    assert result.exit_code == 0, result.output
    return result


def test_teach_json(runner, cli_app, tmp_path):
    out = tmp_path / "run"
    res = _ok(runner.invoke(cli_app, ["sim", "teach", "-o", str(out), "--route", "room3", "--spacing", "0.5", "--json"]))
    summary = json.loads(res.stdout)
    assert summary["frames"] == len(list(out.glob("*.png"))) >= 8
    assert summary["route"] == "room3" and summary["world"] == "default"
    assert load_camera(summary["camera"]).width == 320
    assert (out / "poses.csv").read_text().startswith("image,x,z,theta")


def test_teach_with_options_and_textures(runner, cli_app, tmp_path):
    photos = tmp_path / "photos"
    photos.mkdir()
    cv2.imwrite(str(photos / "wall.png"), np.random.default_rng(0).integers(0, 255, (96, 64, 3), dtype=np.uint8))
    out = tmp_path / "omni"
    res = _ok(runner.invoke(cli_app, [
        "sim", "teach", "-o", str(out), "--world", "3", "--route", "room1", "--vehicle", "omni",
        "--disturbance", "bias,bias_omega_rps=0.1", "--textures", str(photos), "--spacing", "1.0", "--size", "160x120",
    ]))
    assert "images of route 'room1'" in res.stdout
    assert cv2.imread(str(out / "0000.png")).shape == (120, 160, 3)
    world = load_world(out / "world.json")
    assert any(w.texture.startswith("user:") for w in world.walls)


def test_show_world_and_make_world(runner, cli_app, tmp_path):
    plan = tmp_path / "plan.png"
    res = _ok(runner.invoke(cli_app, ["sim", "show-world", "default", "-o", str(plan), "--json"]))
    info = json.loads(res.stdout)
    assert "loop" in info["routes"] and info["walls"] > 40
    assert cv2.imread(str(plan)) is not None
    wfile = tmp_path / "w.json"
    _ok(runner.invoke(cli_app, ["sim", "make-world", "--seed", "9", "--lattice", "4x3", "-o", str(wfile)]))
    assert load_world(wfile).seed == 9
    plan2 = tmp_path / "plan2.png"
    res = _ok(runner.invoke(cli_app, ["sim", "show-world", str(wfile), "-o", str(plan2), "--route", "room1"]))
    assert "room1" in res.stdout and plan2.exists()


def test_render(runner, cli_app, tmp_path):
    out = tmp_path / "view.png"
    _ok(runner.invoke(cli_app, ["sim", "render", "0", "-o", str(out), "--size", "200x100"]))
    assert cv2.imread(str(out)).shape == (100, 200, 3)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["sim", "teach", "-o", "{tmp}/a", "--disturbance", "gale"], "unknown disturbance preset 'gale'"),
        (["sim", "teach", "-o", "{tmp}/a", "--vehicle", "tank"], "unknown vehicle 'tank'"),
        (["sim", "teach", "-o", "{tmp}/a", "--route", "attic"], "unknown route 'attic'"),
        (["sim", "teach", "-o", "{tmp}/a", "--world", "{tmp}/missing.json"], "neither a seed"),
        (["sim", "teach", "-o", "{tmp}/a", "--world", "{tmp}/corrupt.json"], "not valid JSON"),
        (["sim", "teach", "-o", "{tmp}/a", "--size", "big"], "--size"),
        (["sim", "teach", "-o", "{tmp}/a", "--spacing", "0"], "spacing"),
        (["sim", "teach", "-o", "{tmp}/a", "--textures", "{tmp}/nowhere"], "does not exist"),
        (["sim", "show-world", "{tmp}/notworld.json", "-o", "{tmp}/p.png"], "not a topomap world"),
        (["sim", "render", "default", "-o", "{tmp}/v.png", "--pose", "1,2"], "--pose"),
        (["sim", "render", "default", "-o", "{tmp}/v.png", "--pose", "-50,-50,0"], "inside a wall"),
        (["sim", "teach"], "Missing option"),
        (["sim", "teach", "-o", "{tmp}/a", "--spacing", "0.000001"], "too small; use at least 0.01"),
        (["sim", "show-world", "default", "-o", "{tmp}/w.txt"], "give a file name ending in one of .png"),
        (["sim", "render", "default", "-o", "{tmp}/w.txt"], "give a file name ending in one of .png"),
        (["sim", "make-world", "--seed", "-1", "-o", "{tmp}/w.json"], "world seed -1 must be an integer from 0"),
        (["sim", "render", "/dev/zero", "-o", "{tmp}/v.png"], "not a regular file"),
        (["sim", "render", "{tmp}/nested.json", "-o", "{tmp}/v.png"], "nests its JSON too deeply"),
    ],
)
def test_bad_input_is_one_line_and_exit_1(runner, cli_app, tmp_path, args, message):
    (tmp_path / "corrupt.json").write_text("{oops")
    (tmp_path / "nested.json").write_text("[" * 200_000 + "]" * 200_000)
    (tmp_path / "notworld.json").write_text('{"hello": 1}')
    res = runner.invoke(cli_app, [a.replace("{tmp}", str(tmp_path)) for a in args])
    assert res.exit_code == 1, res.output
    err = res.stderr.strip()
    assert len(err.splitlines()) == 1 and err.startswith("Error:"), err
    assert message in err
