"""Worlds: generator, geometry, routes, JSON files, textures."""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from topomap.errors import ConfigError, DatasetError
from topomap.sim import textures as tx
from topomap.sim.world import TILE_VARIANTS, World, default_world, generate_world, load_world, resolve_world

from sim.sim_helpers import box_world


def test_same_seed_same_world_other_seed_other_world():
    a, b, c = generate_world(3), generate_world(3), generate_world(4)
    assert a == b
    assert a.to_dict() == b.to_dict()
    assert a != c


def test_default_world_has_corridors_rooms_junctions_and_a_loop(world):
    loop = world.route("loop")
    assert loop.closed and loop.waypoints[0] == loop.waypoints[-1]
    assert loop.length_m > 30.0
    assert sum(name.startswith("room") for name in world.route_names) >= 3
    assert world.wall_height_m == pytest.approx(2.5)
    # Junctions: points with long free runs in at least 3 of the 4 axis directions (corners of the
    # loop have 2; rooms are too small for runs of 3.5 m on 3 sides).
    def run(x, z, dx, dz):
        n = 0
        while n < 40 and world.is_free(x + (n + 1) * 0.1 * dx, z + (n + 1) * 0.1 * dz):
            n += 1
        return n * 0.1

    x0, z0, x1, z1 = world.bounds()
    junctions = [
        (x, z)
        for x in np.arange(x0, x1, 0.5)
        for z in np.arange(z0, z1, 0.5)
        if world.is_free(x, z) and sum(run(x, z, dx, dz) >= 3.5 for dx, dz in ((1, 0), (-1, 0), (0, 1), (0, -1))) >= 3
    ]
    assert junctions


@pytest.mark.parametrize("seed", [0, 1, 5])
def test_routes_stay_clear_of_walls(seed):
    w = generate_world(seed)
    for r in w.routes:
        p = r.points
        for a, b in zip(p[:-1], p[1:]):
            for f in np.linspace(0.0, 1.0, max(2, int(np.linalg.norm(b - a) / 0.1))):
                x, z = a + f * (b - a)
                assert w.is_free(x, z), (r.name, x, z)
                assert w.clearance(x, z) > 0.45, (r.name, x, z)


def test_walls_face_the_free_space(world):
    for wl in world.walls:
        d = np.array([wl.x1 - wl.x0, wl.z1 - wl.z0]) / wl.length
        left = np.array([-d[1], d[0]])
        mid = np.array([(wl.x0 + wl.x1) / 2, (wl.z0 + wl.z1) / 2])
        assert world.is_free(*(mid + 0.05 * left))
        assert not world.is_free(*(mid - 0.05 * left))


def test_json_round_trip(tmp_path, world):
    path = world.save(tmp_path / "w.json")
    back = load_world(path)
    assert back == world
    assert back.route("loop").waypoints == world.route("loop").waypoints
    assert path.stat().st_size < 100_000  # a small file


def test_resolve_world_spec(tmp_path, world):
    assert resolve_world("default") == world
    assert resolve_world("2") == generate_world(2)
    assert resolve_world(str(world.save(tmp_path / "w.json"))) == world
    with pytest.raises(DatasetError, match="neither a seed"):
        resolve_world(str(tmp_path / "missing.json"))


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("{not json", "not valid JSON"),
        ('{"walls": []}', "not a topomap world file"),
        ('{"format": "topomap-world", "version": 99, "walls": []}', "newer topomap"),
        ('{"format": "topomap-world", "version": 1, "walls": [[0, 0, 1]], "free": []}', "corrupt"),
        ('{"format": "topomap-world", "version": 1, "free": [[0, 0, 1, 1]]}', "corrupt"),
        ('{"format": "topomap-world", "version": 1, "walls": [[0, 0, 0, 0, "proc:poster:1"]], "free": [[0, 0, 1, 1]]}', "corrupt"),
    ],
)
def test_bad_world_files(tmp_path, text, match):
    p = tmp_path / "bad.json"
    p.write_text(text)
    with pytest.raises(DatasetError, match=match):
        load_world(p)


def test_missing_world_file(tmp_path):
    with pytest.raises(DatasetError, match="does not exist"):
        load_world(tmp_path / "nope.json")


def test_unknown_route_lists_choices(world):
    with pytest.raises(ConfigError, match="loop"):
        world.route("garage")


def test_generator_rejects_bad_parameters():
    with pytest.raises(DatasetError):
        generate_world(0, lattice=(1, 3))
    with pytest.raises(DatasetError):
        generate_world(0, spacing_m=(2.0, 3.0))


def test_bigger_lattice_has_more_routes_and_walls():
    small, big = generate_world(7, lattice=(2, 2)), generate_world(7, lattice=(4, 3), rooms=6)
    assert big.route("loop").length_m > small.route("loop").length_m
    assert len(big.walls) > len(small.walls)


def test_textures_are_deterministic_and_mirrorable():
    a = tx.texture_image("proc:poster:5")
    assert a.shape == (256, 256, 3) and a.dtype == np.uint8
    assert np.array_equal(a, tx.texture_image("proc:poster:5"))
    assert not np.array_equal(a, tx.texture_image("proc:poster:6"))
    key = tx.photo_keys()[0]
    assert np.array_equal(tx.texture_image(key + ":flip"), tx.texture_image(key)[:, ::-1])
    with pytest.raises(ConfigError, match="poster"):
        tx.texture_image("proc:marble:1")
    with pytest.raises(DatasetError):
        tx.texture_image("photo:not_shipped")


def test_world_photographs_used_once_each(world):
    photos = [w.texture for w in world.walls if w.texture.startswith("photo:")]
    assert len(photos) >= 10
    assert len(set(photos)) == len(photos)


def test_user_textures(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(3):
        cv2.imwrite(str(folder / f"p{i}.png"), rng.integers(0, 255, (64, 48, 3), dtype=np.uint8))
    (folder / "notes.txt").write_text("not an image")
    w = generate_world(0, textures=folder)
    users = {wl.texture.removesuffix(":flip") for wl in w.walls if wl.texture.startswith("user:")}
    assert users == {"user:p0.png", "user:p1.png", "user:p2.png"}
    assert not any(wl.texture.startswith("photo:") for wl in w.walls)
    assert tx.texture_image("user:p1.png", w.texture_dir).shape == (64, 48, 3)
    # The same plan with other photographs.
    again = default_world().retextured(folder)
    assert [wl.x0 for wl in again.walls] == [wl.x0 for wl in default_world().walls]
    assert any(wl.texture.startswith("user:") for wl in again.walls)
    # Saved worlds remember the folder.
    assert load_world(w.save(tmp_path / "w.json")).texture_dir == str(folder.resolve())


def test_empty_or_missing_texture_folder(tmp_path):
    with pytest.raises(DatasetError, match="no .jpg/.png"):
        generate_world(0, textures=tmp_path)
    with pytest.raises(DatasetError, match="does not exist"):
        generate_world(0, textures=tmp_path / "nowhere")


def test_world_validation():
    good = box_world(5.0)
    with pytest.raises(DatasetError, match="no walls"):
        World(walls=(), free=good.free)
    with pytest.raises(DatasetError, match="wall height"):
        World(walls=good.walls, free=good.free, wall_height_m=0.0)
    data = good.to_dict()
    json.dumps(data)  # JSON-able
    assert World.from_dict(data) == good


def test_tile_variants_in_world_files(tmp_path, world):
    assert world.tile_variants == TILE_VARIANTS > 1  # generated worlds: a floor that never repeats
    data = world.to_dict()
    assert data["version"] == 2 and data["tile_variants"] == TILE_VARIANTS
    old = {k: v for k, v in data.items() if k != "tile_variants"}
    old["version"] = 1  # written before variants: one texture tiled everywhere, as it was taught
    assert World.from_dict(old).tile_variants == 1
    for bad in (0, 65, "16", True, 2.5, None):
        with pytest.raises(DatasetError, match="tile_variants"):
            World.from_dict({**data, "tile_variants": bad})
    huge = {**data, "free": [[0, 0, 400, 400]]}  # the renderer would cut it into 160 000 cells
    with pytest.raises(DatasetError, match="more than the 100000 m2"):
        World.from_dict(huge)


def test_hostile_world_files_are_refused_before_anything_is_built(tmp_path, world):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from fuzz_cases import world_attacks

    expected = {
        "floor_texture_negative_seed": "needs a seed from 0", "texture_escape": "inside its texture folder",
        "texture_absolute": "inside its texture folder", "marker_colour_huge": "between 0 and 255",
        "marker_radius_inf": "marker radius_m", "wall_height_huge": "wall height", "walls_not_list": "must be",
        "wall_short_row": "a wall must be", "many_walls": "6000 walls, more than the 5000",
        "route_huge": "at most 10000 waypoints", "seed_text": "seed must be", "name_huge": "longer than 200",
        "nested_arrays": "nests its JSON too deeply", "tile_variants_huge": "tile_variants",
        "free_floor_huge": "more than the 100000 m2",
    }
    attacks = world_attacks(world.to_dict())
    assert set(attacks) == set(expected)
    for name, w in attacks.items():
        f = tmp_path / f"{name}.json"
        f.write_text(w if isinstance(w, str) else json.dumps(w))
        t0 = time.perf_counter()
        with pytest.raises(DatasetError, match=expected[name]):
            load_world(f)
        assert time.perf_counter() - t0 < 5.0, name


def test_world_files_that_never_end_are_not_read(tmp_path):
    sparse = tmp_path / "sparse.json"
    with open(sparse, "wb") as fh:
        fh.truncate(2 << 30)  # 2 GB, no disk used
    with pytest.raises(DatasetError, match="2048 MB, more than the 16 MB"):
        load_world(sparse)
    os.mkfifo(tmp_path / "fifo.json")
    for f in (tmp_path / "fifo.json", Path("/dev/zero")):
        with pytest.raises(DatasetError, match="not a regular file"):
            resolve_world(str(f))
    with pytest.raises(DatasetError, match="is a folder"):
        load_world(tmp_path)


def test_texture_keys_stay_in_their_folder(tmp_path):
    for key in ("user:../x.jpg", "user:/etc/passwd", "photo:../../etc/x", "user:..", "user:a/b.png"):
        with pytest.raises(DatasetError, match="inside its texture folder"):
            tx.texture_image(key, tmp_path)
    with pytest.raises(DatasetError, match="seed from 0"):
        tx.texture_image("proc:tiles:-5")
    tx.check_texture_key("user:wall one.jpg:flip")


def test_texture_photograph_bomb_is_skipped_with_its_reason(tmp_path, caplog):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from fuzz_cases import png_bomb

    (tmp_path / "bomb.png").write_bytes(png_bomb(20000, 20000, channels=3))
    cv2.imwrite(str(tmp_path / "ok.jpg"), np.full((64, 64, 3), 128, np.uint8))
    assert tx.photo_keys(tmp_path) == ["user:ok.jpg"]
    assert "declares 20000x20000 pixels" in caplog.text


def test_negative_seeds_are_refused():
    with pytest.raises(DatasetError, match="from 0 to 2"):
        generate_world(-1)
    with pytest.raises(DatasetError, match="from 0 to 2"):
        resolve_world("-3")


# ---------------------------------------------------------------------- office style
def test_existing_procedural_textures_keep_their_pixels():
    # the office kinds were added with their own random streams: worlds made before keep their look
    import hashlib

    got = [hashlib.sha1(tx.texture_image(f"proc:{k}:5").tobytes()).hexdigest()[:10]
           for k in ("board", "bricks", "ceiling", "panels", "poster", "tiles")]
    assert got == ["05e6fbc8b6", "1825afc615", "9369d721bc", "3ff1840c91", "681f5473ef", "abdd585d53"]


def test_office_world_is_the_seed_floor_plan_with_plain_walls_and_few_features():
    from topomap.sim.world import office_world

    plain, office = generate_world(3), office_world(3)
    assert np.array_equal(plain.segments, office.segments) and plain.routes == office.routes
    assert office.name == "office3" and office == resolve_world("office:3")
    kinds = [w.texture.split(":")[1] if w.texture.startswith("proc:") else "photo" for w in office.walls]
    share = {k: kinds.count(k) / len(kinds) for k in set(kinds)}
    assert "photo" not in share and share["paint"] > 0.45
    assert 0.03 < share.get("frame", 0) < 0.2 and share.get("door", 0) > 0.05 and share.get("fitting", 0) > 0.1
    orb = cv2.ORB_create(500)

    def features(key):
        return len(orb.detect(cv2.cvtColor(tx.texture_image(key), cv2.COLOR_RGB2GRAY), None))

    paint = [features(f"proc:paint:{s}") for s in range(5)]
    poster = [features(f"proc:poster:{s}") for s in range(5)]
    assert max(paint) < 0.2 * min(poster)  # plain paint offers local features almost nothing


def test_world_presets_in_specs_and_bad_ones():
    assert resolve_world("office").name == "office0"
    with pytest.raises(DatasetError, match="must be an integer"):
        resolve_world("office:x")
    with pytest.raises(ConfigError, match="unknown world style 'gallery'"):
        generate_world(1, style="gallery")
