"""The held-out navigation benchmark's bookkeeping: failure kinds, time budget, Wilson interval, seeds."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

_ROOT = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture(scope="module")
def bench():
    sys.path.insert(0, str(_ROOT))
    spec = importlib.util.spec_from_file_location("bench_navigate_unseen", _ROOT / "bench_navigate_unseen.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _row(**kw):
    return {"success": False, "status": "failed", "message": "", **kw}


def test_failure_kinds_from_outcome_and_events(bench):
    k = bench.failure_kind
    assert k(_row(success=True, status="arrived")) == (None, None)
    assert k(_row(status="arrived"))[0] == "false arrival"
    assert k(_row(status="timeout", message="time budget of 300 s exhausted at subgoal 4"))[0] == "timeout"
    assert k(_row(message="could not localize in the map after a full turn (best confidence 0.20)"))[0] == "no localization"
    assert k(_row(message="gave up after 8 re-plans (lost sight of subgoal 86)"))[0] == "gave up (lost)"
    assert k(_row(message="gave up after 8 re-plans (was fooled by a look-alike of subgoal 3)"))[0] == "gave up (fooled)"
    assert k(_row(message="gave up after 8 re-plans (could not reach subgoal 9)"))[0] == "gave up (stuck)"
    tried = "; tried: backed off 12 s toward nodes that verified well, turned 720 deg in place searching, re-localized 9 times (1 far); 80 s of 340 s left)"
    tried = tried.replace("; 80 s", ", reversed out of contact 2 times, ended 1 back-offs at contact; 80 s")
    for why, kind in (("lost sight of", "lost"), ("was fooled by a look-alike of", "fooled"), ("could not reach", "stuck"),
                      ("was blocked on the way to", "blocked")):
        assert k(_row(message=f"gave up after 9 re-plans ({why} subgoal 9{tried}"))[0] == f"gave up ({kind})"
    wrong = _row(message="gave up after 8 re-plans (lost sight of subgoal 86)", start_localization_error_m=11.0)
    assert k(wrong) == ("wrong start localization", "gave up (lost)")
    turned = _row(status="timeout", start_localization_error_m=0.3, start_localization_error_deg=170.0)
    assert k(turned) == ("wrong start localization", "timeout")
    assert k(_row(status="replayed"))[0] == "off target"


def test_budget_follows_the_navigators_rule(bench):
    events = [{"kind": "localized", "t": 0.0, "hops": 0}, {"kind": "planned", "t": 0.5, "hops": 20},
              {"kind": "lost", "t": 100.0, "hops": 20}, {"kind": "replanned", "t": 110.0, "hops": 30},
              {"kind": "replanned", "t": 120.0, "hops": 2}]
    assert bench._budget(events, 10.0) == pytest.approx(110.0 + 60.0 + 300.0)
    assert bench._budget(events[:2], 10.0) == pytest.approx(260.0)
    # only the first max_replans re-plans extend the budget
    many = events[:2] + [{"kind": "replanned", "t": 100.0 * k, "hops": 20} for k in range(1, 20)]
    n = bench.NavigateConfig().max_replans
    assert bench._budget(many, 10.0) == pytest.approx(100.0 * n + 60.0 + 200.0)


def test_wilson_interval_and_world_ranges(bench):
    lo, hi = bench.wilson(95, 100)
    assert lo == pytest.approx(0.8882, abs=1e-3) and hi == pytest.approx(0.9785, abs=1e-3)
    lo, hi = bench.wilson(10, 10)
    assert hi == pytest.approx(1.0) and lo == pytest.approx(0.7225, abs=1e-3)
    assert bench.parse_worlds("100-103,110") == [100, 101, 102, 103, 110]
    assert not set(bench.HELD_OUT_WORLDS) & set(bench.TUNING_WORLDS)


def test_summary_counts_failures_and_early_give_ups(bench):
    rows = []
    for i in range(10):
        ok = i < 8
        rows.append({"method": "topomap", "vehicle": ("unicycle", "omni")[i % 2], "success": ok,
                     "status": "arrived" if ok else "failed", "final_position_error_m": 0.02 * (i + 1),
                     "final_heading_error_deg": 1.0, "wall_s": 10.0, "duration_s": 50.0, "budget_s": 300.0,
                     "message": "" if ok else "gave up after 8 re-plans (lost sight of subgoal 5)",
                     "kind": None if ok else "gave up (lost)"})
    s = bench.summarize(rows)["topomap"]
    assert s["all"]["arrived"] == 8 and s["all"]["failures"] == {"gave up (lost)": 2}
    assert s["all"]["median_error_m"] == pytest.approx(0.11)
    assert s["gave_up_with_quarter_budget_left"] == 2


def test_servo_and_navigate_ablations_parse_like_the_other_options(bench):
    from topomap.config import ServoConfig
    from topomap.errors import ConfigError

    nav = bench.config_overrides(bench.NavigateConfig(), "arrive_floor_max_m=0.12,distrust_loop_after=0", "--navigate")
    assert nav.arrive_floor_max_m == 0.12 and nav.distrust_loop_after == 0
    assert bench.config_overrides(ServoConfig(), "pose_window=1").pose_window == 1
    assert bench.config_overrides(ServoConfig(), None) == ServoConfig()
    with pytest.raises(ConfigError, match="--navigate distrust_loop_after='two' must be a whole number"):
        bench.config_overrides(bench.NavigateConfig(), "distrust_loop_after=two", "--navigate")
    with pytest.raises(ConfigError, match="distrust_loop_after"):  # the config's own check
        bench.config_overrides(bench.NavigateConfig(), "distrust_loop_after=-1", "--navigate")


def test_the_baseline_spreads_over_the_worlds(bench):
    # ten worlds of ten episodes, every 10th: one baseline episode per world, both vehicles
    picked = [(k, w) for k in range(10) for w in range(10) if bench.runs_baseline(k, w, 10)]
    assert len(picked) == 10 and {w for _, w in picked} == set(range(10))
    assert {k % 2 for k, _ in picked} == {0, 1}  # episodes alternate unicycle / omni
    assert all(bench.runs_baseline(k, w, 1) for k in range(3) for w in range(3))
