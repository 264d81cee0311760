"""Maps of every released schema version (tests/data/corridor-schemaN.topomap) open, localize and
upgrade: read-only migration in memory, ``upgrade_map`` / ``topomap upgrade`` rewriting atomically,
and the first write upgrading an old map on its own."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest
from conftest import assert_error, tamper
from fuzz_cases import map_signature

import topomap.store as store
from topomap.images import read_image
from topomap.localize import Localizer
from topomap.errors import MapFormatError
from topomap.store import SCHEMA_VERSION, SCHEMAS, load_map, open_for_update, upgrade_map

DATA = Path(__file__).parent / "data"
DEMO = Path(__file__).resolve().parents[1] / "datasets" / "demo" / "corridor"
FIXTURES = sorted(DATA.glob("corridor-schema*.topomap"))
HELD_OUT = (3, 7, 9)  # demo frames not in the fixture maps


def version_of(path: Path) -> int:
    return int(re.search(r"schema(\d+)", path.name).group(1))


def files_in(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


def test_every_released_schema_has_a_fixture():
    assert sorted(version_of(f) for f in FIXTURES) == sorted(SCHEMAS)
    assert SCHEMA_VERSION == max(SCHEMAS)


@pytest.fixture(params=FIXTURES, ids=lambda p: p.name)
def fixture_copy(request, tmp_path):
    return Path(shutil.copy(request.param, tmp_path / request.param.name))


def test_fixture_opens_read_only_and_localizes(fixture_copy):
    before = (fixture_copy.read_bytes(), fixture_copy.stat().st_mtime_ns, files_in(fixture_copy.parent))
    m = load_map(fixture_copy, images=True)
    assert (fixture_copy.read_bytes(), fixture_copy.stat().st_mtime_ns, files_in(fixture_copy.parent)) == before
    assert m.meta["schema_version"] == version_of(fixture_copy) == store.map_schema_version(fixture_copy)
    assert len(m.sequences) == 2 and m.index is not None and all(n.image is not None for n in m.nodes.values())
    loc = Localizer(m)
    for i in HELD_OUT:
        r = loc.localize(read_image(DEMO / f"{i:07d}.jpg"))
        place = int(Path(m.nodes[r.node].source).stem)  # corridor frames are named by their index
        assert r.localized and abs(place - i) <= 2, (i, r.node, m.nodes[r.node].source, r.status)


def test_upgrade_rewrites_the_same_map_in_the_current_schema(fixture_copy):
    migrated = load_map(fixture_copy, images=True)
    old, new = upgrade_map(fixture_copy)
    assert (old, new) == (version_of(fixture_copy), SCHEMA_VERSION)
    assert files_in(fixture_copy.parent) == [fixture_copy.name]  # no temporary file left
    upgraded = load_map(fixture_copy, images=True)
    assert upgraded.meta["schema_version"] == SCHEMA_VERSION
    assert map_signature(upgraded)[:7] == map_signature(migrated)[:7]  # nodes, edges, frames, runs, camera, config, index
    data = fixture_copy.read_bytes()
    assert upgrade_map(fixture_copy) == (SCHEMA_VERSION, SCHEMA_VERSION)
    assert fixture_copy.read_bytes() == data  # a current map is left untouched


def test_first_write_upgrades_an_old_map(fixture_copy):
    with open_for_update(fixture_copy) as u:
        assert u.map.meta["schema_version"] == SCHEMA_VERSION
        u.map.meta["note"] = "added"
        u.commit()
    m = load_map(fixture_copy)
    assert m.meta["note"] == "added" and m.meta["schema_version"] == SCHEMA_VERSION


def test_cli_upgrade(runner, cli_app, fixture_copy):
    result = runner.invoke(cli_app, ["upgrade", str(fixture_copy)])
    assert result.exit_code == 0, result.output
    expected = "already uses" if version_of(fixture_copy) == SCHEMA_VERSION else f"from map schema {version_of(fixture_copy)} to {SCHEMA_VERSION}"
    assert expected in result.stdout
    info = json.loads(runner.invoke(cli_app, ["info", str(fixture_copy), "--json"]).stdout)
    assert info["schema_version"] == SCHEMA_VERSION and info["nodes"] == 6
    assert_error(runner.invoke(cli_app, ["upgrade", str(fixture_copy.parent / "none.topomap")]), "does not exist")


def test_old_map_info_says_it_can_be_upgraded(runner, cli_app, tmp_path):
    old = Path(shutil.copy(DATA / "corridor-schema1.topomap", tmp_path / "old.topomap"))
    result = runner.invoke(cli_app, ["info", str(old)])
    assert result.exit_code == 0 and "topomap upgrade" in result.stdout
    assert json.loads(runner.invoke(cli_app, ["info", str(old), "--json"]).stdout)["schema_version"] == 1


def test_upgrade_refuses_a_damaged_old_map(tmp_path):
    old = Path(shutil.copy(DATA / "corridor-schema1.topomap", tmp_path / "old.topomap"))
    tamper(old, "UPDATE edge SET similarity = 7")  # schema 1 has no checksums: the range check finds it
    before = old.read_bytes()
    with pytest.raises(MapFormatError, match="out-of-range"):
        upgrade_map(old)
    assert old.read_bytes() == before and files_in(tmp_path) == ["old.topomap"]
