"""Shared fixtures: where the real datasets live, scratch folders, the CLI runner."""

from __future__ import annotations

import os
import shutil
import sqlite3
from collections.abc import Callable
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


def built_once(tmp_path_factory, name: str, make: Callable[[Path], object]) -> Path:
    """The file or folder ``name`` that ``make(path)`` writes, made once per test session and shared
    by every pytest-xdist worker (under a lock in the session's base folder; the others wait for it):
    for what several test files build the same way (the corridor map with the defaults, ~30 s a build)."""
    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        base = base.parent  # each worker's base folder lies in the session's, which they all share
    try:
        import fcntl
    except ImportError:  # pragma: no cover - no POSIX locks (Windows): each worker makes its own
        fcntl, base = None, tmp_path_factory.getbasetemp()
    path = base / "built-once" / name
    path.parent.mkdir(exist_ok=True)
    done = path.with_name(name + ".done")  # written once make() returned: the path is whole
    with open(path.with_name(name + ".lock"), "w") as lock:
        if fcntl is not None:
            fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.exists():
            if path.is_dir():  # left half made by a make() that failed
                shutil.rmtree(path)
            elif path.exists():
                path.unlink()
            make(path)
            done.touch()
    return path


def corridor_map_file(tmp_path_factory) -> Path:
    """The corridor map (built from ref/ with the defaults), built once per test session and shared
    by test_build.py, test_localize.py, test_cli_localize.py and test_cli_build.py. Copy it before
    changing it."""
    from topomap.build import build_map
    from topomap.store import save_map

    ref = dataset("corridor") / "ref"
    return built_once(tmp_path_factory, "corridor.topomap", lambda path: save_map(build_map(ref), path))


def walk_map_file(tmp_path_factory) -> tuple[Path, Path]:
    """(image folder, map file) of map_synth's out-and-back walk built with its FAST settings, once
    per test session, shared by test_build.py and test_agreement.py. Copy the map before changing it."""
    from map_synth import FAST, write_out_and_back

    from topomap.build import build_map
    from topomap.store import save_map

    def make(root: Path) -> None:
        write_out_and_back(root / "imgs")
        save_map(build_map(root / "imgs", FAST), root / "walk.topomap")

    root = built_once(tmp_path_factory, "walk", make)
    return root / "imgs", root / "walk.topomap"


def castle_map_file(tmp_path_factory) -> Path:
    """The castle-p30 map (its images with K.txt, the defaults, in this process), built once per test
    session and shared by test_build.py and test_parallel.py. Copy it before changing it."""
    from topomap.build import build_map
    from topomap.camera import load_camera
    from topomap.store import save_map

    root = dataset("castle-p30")
    return built_once(tmp_path_factory, "castle.topomap",
                      lambda path: save_map(build_map(root / "images", camera=load_camera(root / "K.txt")), path))


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
    ``rrd`` is None when the viz extra (rerun-sdk) is not installed. Made once per test session
    (shared by the xdist workers): treat it as read-only."""
    import importlib.util
    import json

    has_rerun = importlib.util.find_spec("rerun") is not None

    def make(root: Path) -> None:
        from typer.testing import CliRunner

        from topomap.sim.teach import teach
        from topomap.sim.world import default_world
        from topomap_cli.main import app

        run = teach(default_world(), "room3", root / "teach")
        runner = CliRunner()
        res = runner.invoke(app, ["build", str(root / "teach"), "--camera", str(run.camera_path), "-o", str(root / "m.topomap"), "--json"])
        assert res.exit_code == 0, res.output
        args = ["navigate", str(root / "m.topomap"), "--goal", "4", "--start-node", "0", "--record", str(root / "rec"), "--json"]
        res = runner.invoke(app, args + (["--rerun", str(root / "run.rrd")] if has_rerun else []))
        assert res.exit_code == 0, res.output
        (root / "result.json").write_text(res.stdout)

    root = built_once(tmp_path_factory, "shortrun", make)
    return {"root": root, "teach": root / "teach", "map": root / "m.topomap", "record": root / "rec",
            "rrd": root / "run.rrd" if has_rerun else None, "result": json.loads((root / "result.json").read_text())}
