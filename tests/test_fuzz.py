"""Fuzz and fault cases regenerated from seeds (tests/fuzz_cases.py): byte flips and truncations of
a map, tampered rows (with and without recomputed checksums), views/triggers/extra tables, image
bombs as files, bytes and map BLOBs, SIGKILL during a commit, concurrent writers, hostile worlds
and input folders. Each must end in one clean error or in a success that lost nothing, within a
deadline. ``benchmarks/fuzz_maps.py`` runs thousands of them with other seeds and counts outcomes.
"""

from __future__ import annotations

import contextlib
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import cv2
import pytest
from fuzz_cases import CASE_KINDS, ERROR, OK, SCHEMA_ATTACKS, TAMPERS, FuzzContext, make_base_map, map_signature

from topomap.store import load_map

#: kind -> (number of seeds in CI, outcomes allowed)
PLAN = {
    "flip": (120, {OK, ERROR}),
    "truncate": (20, {OK, ERROR}),
    "tamper": (2 * len(TAMPERS), {ERROR}),
    "schema": (len(SCHEMA_ATTACKS), {ERROR}),
    "image_bomb": (14, {ERROR}),
    "map_bomb": (14, {ERROR}),
    "kill_commit": (8, {OK}),
    "concurrent": (6, {OK}),
    "world": (17, {ERROR}),
    "inputs": (6, {OK}),
}
DEADLINE_S = 20  # each case, far above its usual 0.01-1 s: a hang fails instead of blocking CI


@pytest.fixture(scope="session")
def fuzz_base(tmp_path_factory):
    root = tmp_path_factory.mktemp("fuzzbase")
    base = make_base_map(root)
    m = load_map(base, images=True)
    query = cv2.imread(str(sorted((root / "frames").iterdir())[2]), cv2.IMREAD_GRAYSCALE)
    return base, query, map_signature(m), root / "grow"


@contextlib.contextmanager
def deadline(seconds: float):
    """Fail (rather than hang) when the block runs longer than ``seconds``."""
    def expired(*_):
        raise TimeoutError(f"still running after {seconds} s")

    old = signal.signal(signal.SIGALRM, expired)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


@pytest.mark.skipif(sys.platform == "win32", reason="fork, FIFOs and POSIX signals")
@pytest.mark.parametrize("kind,seed", [(k, s) for k, (n, _) in PLAN.items() for s in range(n)])
def test_fuzz_case(kind, seed, fuzz_base, tmp_path):
    base, query, signature, grow = fuzz_base
    ctx = FuzzContext(base, query, tmp_path, signature, grow)
    with deadline(DEADLINE_S):
        outcome = CASE_KINDS[kind](ctx, seed)
    assert outcome.split(": ")[0] in PLAN[kind][1], f"{kind} seed {seed}: {outcome}"


def test_base_map_is_intact(fuzz_base):
    """The cases work on copies: the shared base map still opens with the same content."""
    base, _, signature, _ = fuzz_base
    assert map_signature(load_map(base, images=True)) == signature



def _cli_peak(args: list[str]) -> tuple[int, str, float]:
    """(exit code, stderr, peak RSS [MB]) of ``topomap ARGS`` in a fresh process."""
    code = ("import resource, subprocess, sys; p = subprocess.run(sys.argv[1:], capture_output=True, text=True); "
            "sys.stdout.write(p.stderr); print(p.returncode, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)")
    out = subprocess.run([sys.executable, "-c", code, sys.executable, "-m", "topomap_cli.main", *args],
                         capture_output=True, text=True, timeout=120).stdout.strip().splitlines()
    rc, kb = out[-1].split()
    return int(rc), "\n".join(out[:-1]), int(kb) / 1024


@pytest.mark.slow
@pytest.mark.slow
@pytest.mark.skipif(sys.platform != "linux", reason="ru_maxrss in KB")
def test_bombs_stay_under_500_mb_through_the_cli(fuzz_base, tmp_path):
    from fuzz_cases import jpeg_declaring, png_bomb, reseal

    base, _, _, grow = fuzz_base
    m = Path(shutil.copy(base, tmp_path / "bomb.topomap"))
    con = sqlite3.connect(m)
    con.execute("UPDATE node SET thumbnail = ?", (png_bomb(30000, 30000),))
    con.commit()
    con.close()
    reseal(m)
    frames = tmp_path / "frames"
    shutil.copytree(grow, frames)
    (frames / "0_bomb.png").write_bytes(png_bomb(30000, 30000))
    (tmp_path / "q.jpg").write_bytes(jpeg_declaring(30000, 30000, colour=True))
    for args, expect in ((["info", str(m)], "declares 30000x30000 pixels"),
                         (["localize", str(base), str(tmp_path / "q.jpg")], "declares 30000x30000 pixels"),
                         # --workers 1: no pool to start; the bomb sorts first, and the build reads its
                         # frames up to the first readable one in its own process with any worker count
                         (["build", str(frames), "-o", str(tmp_path / "b.topomap"), "--json", "--workers", "1"], None)):
        t0 = time.perf_counter()
        rc, err, mb = _cli_peak(args)
        assert time.perf_counter() - t0 < 30 and mb < 500, (args[0], mb)
        if expect is None:
            assert rc == 0, err
        else:
            lines = [ln for ln in err.splitlines() if ln.strip()]
            assert rc == 1 and len(lines) == 1 and lines[0].startswith("Error:") and expect in lines[0], err
