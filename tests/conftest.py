"""Shared fixtures: where the real datasets live, scratch folders, the CLI runner."""

from __future__ import annotations

import os
import sqlite3
from pathlib import Path

import pytest

#: ../shared beside the repository (CI puts it there); override with TOPOMAP_SHARED.
SHARED = Path(os.environ.get("TOPOMAP_SHARED", Path(__file__).resolve().parents[1].parent / "shared"))
DATASETS = SHARED / "datasets"


#: Session fixtures that teach a simulated world, build its map and navigate in it (half a minute to
#: minutes each): every test that uses one is marked slow (`pytest -m "not slow"` leaves them out).
SLOW_FIXTURES = frozenset({"demo", "taught", "split_map", "short_run", "recorded"})


def pytest_collection_modifyitems(config, items):
    for item in items:
        if SLOW_FIXTURES.intersection(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.slow)


def dataset(name: str) -> Path:
    """Path of a real dataset under ../shared/datasets, skipping the test when it is absent."""
    p = DATASETS / name
    if not p.exists():
        pytest.skip(f"dataset {name} not found under {DATASETS}")
    return p


@pytest.fixture
def runner():
    from typer.testing import CliRunner

    return CliRunner()


@pytest.fixture
def cli_app():
    from topomap_cli.main import app

    return app


def assert_error(result, *fragments: str, alone: bool = True) -> str:
    """Exit code 1 through SystemExit, no traceback, and exactly one line starting with "Error:"
    (the last line on stderr) containing every fragment; with ``alone`` it is the only output
    (``alone=False`` allows the warnings and progress of frames that were read). Returns the line."""
    assert result.exit_code == 1, (result.exit_code, result.output)
    assert isinstance(result.exception, SystemExit), repr(result.exception)
    assert "Traceback" not in result.output
    lines = [ln for ln in result.stderr.splitlines() if ln.strip()]
    errors = [ln for ln in result.output.splitlines() if ln.startswith("Error:")]
    assert len(errors) == 1 and lines and lines[-1] == errors[0], result.output
    if alone:
        assert len(lines) == 1, result.output
    for f in fragments:
        assert f in errors[0], (f, errors[0])
    assert result.stdout == ""
    return errors[0]


def tamper(path, *statements: str) -> None:
    """Run SQL statements on a map (or any SQLite file) behind topomap's back, and commit."""
    con = sqlite3.connect(path)
    for sql in statements:
        con.execute(sql)
    con.commit()
    con.close()


@pytest.fixture(scope="session")
def short_run(tmp_path_factory):
    """A short navigation recorded every way (issue 18): the default world's route room3 taught,
    built into a map, then `topomap navigate MAP --goal 4 --start-node 0 --record rec/ --rerun
    run.rrd --json`. Returns a dict of paths (root, teach, map, record, rrd) and the parsed result;
    ``rrd`` is None when the viz extra (rerun-sdk) is not installed."""
    import importlib.util
    import json

    from typer.testing import CliRunner

    from topomap.sim.teach import teach
    from topomap.sim.world import default_world
    from topomap_cli.main import app

    root = tmp_path_factory.mktemp("shortrun")
    run = teach(default_world(), "room3", root / "teach")
    runner = CliRunner()
    res = runner.invoke(app, ["build", str(root / "teach"), "--camera", str(run.camera_path), "-o", str(root / "m.topomap"), "--json"])
    assert res.exit_code == 0, res.output
    rrd = root / "run.rrd" if importlib.util.find_spec("rerun") else None
    args = ["navigate", str(root / "m.topomap"), "--goal", "4", "--start-node", "0", "--record", str(root / "rec"), "--json"]
    res = runner.invoke(app, args + (["--rerun", str(rrd)] if rrd else []))
    assert res.exit_code == 0, res.output
    return {"root": root, "teach": root / "teach", "map": root / "m.topomap", "record": root / "rec", "rrd": rrd,
            "result": json.loads(res.stdout)}
