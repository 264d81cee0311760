"""Worlds: generator, geometry, routes, JSON files, textures."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from topomap.errors import ConfigError, DatasetError
from topomap.sim import textures as tx
from topomap.sim.world import World, default_world, generate_world, load_world, resolve_world

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
