"""topomap.observability: exact ranks (docs/theory.md section 2), directions, the observer, the CLI."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import sympy as sp

from topomap.errors import ConfigError
from topomap.observability import (
    DirectionKind,
    System,
    analyze,
    float_rank,
    linear_system,
    symbolic_rank,
    observability_table,
    vehicle_landmark_system,
)
from topomap.observability import jets
from topomap.observability.observer import CONVERGENCE_TIME_S, ObserverConfig, lie_derivatives, simulate


def unobs(vehicle, markers, targets, half, inputs, reading="analytic", order=0, seed=0):
    return analyze(vehicle_landmark_system(vehicle, markers, targets, half, inputs, reading, order), seed=seed,
                   directions=False).unobservable_dimension


# ----------------------------------------------------------------------------- docs/theory.md rows
@pytest.mark.parametrize(
    "config, known, analytic",
    [
        ((3, 0, 0), 0, [0, 0, 0, 0]),  # 3 markers: pose and inputs fully reconstructable
        ((1, 0, 0), 1, [3, 4, 5, 6]),  # 1 marker: rotation about the marker; grows with k
        ((0, 1, 0), 3, [5, 6, 7, 8]),  # 1 target: translation + rotation of the scene
    ],
)
def test_thesis_rows(config, known, analytic):
    m, t, h = config
    assert unobs("unicycle", m, t, h, "known") == known
    assert unobs("omni", m, t, h, "known") == known  # same for both vehicles under known inputs
    assert [unobs("unicycle", m, t, h, "unknown", "analytic", k) for k in range(4)] == analytic


# ----------------------------------------------------------------------------- scalar linear sanity
@pytest.mark.parametrize("abc", [(1, 1, 1), (-2, 3, 5), (0, 1, 1), ("1/2", "-3/4", 7), (2, 0, 1), (2, 1, 0), (0, 0, 0)])
@pytest.mark.parametrize("reading", ["analytic", "polynomial"])
def test_linear_augmented_observable_iff_bc_nonzero(abc, reading):
    a, b, c = abc
    expected = sp.Rational(b) * sp.Rational(c) != 0
    for k in range(4):
        rep = analyze(linear_system(a, b, c, "unknown", reading, k))
        assert rep.state_dimension == k + 2
        assert rep.observable is expected, (abc, reading, k, rep.rank)


def test_linear_b_zero_leaves_exactly_the_inputs_unobservable():
    rep = analyze(linear_system(2, 0, 1, "unknown", "analytic", 2))
    assert rep.unobservable_dimension == 3
    assert all(d.kind is DirectionKind.INPUT for d in rep.directions)
    assert {s for d in rep.directions for s in d.support} == {"d", "d'", "d''"}


# ----------------------------------------------------------------------------- exactness
def test_second_point_confirms_and_seed_does_not_change_the_rank():
    system = vehicle_landmark_system("omni", 2, 0, 0, "unknown", "polynomial", 2)
    reports = [analyze(system, seed=s, directions=False) for s in (0, 1, 7)]
    assert all(r.confirmed and r.ranks[0] == r.ranks[1] for r in reports)
    assert len({r.rank for r in reports}) == 1


def test_rank_mod_p_is_exact_on_a_known_matrix():
    from topomap.observability.analysis import nullspace_mod_p, rank_mod_p

    p = 1073741789
    M = np.array([[1, 2, 3], [2, 4, 6], [0, 1, 1]], dtype=np.int64)
    assert rank_mod_p(M, p) == 2
    (v,) = nullspace_mod_p(M, p, 3)
    assert np.all((M @ v) % p == 0) and v.any()
    # a matrix singular only modulo p: over Q it has full rank
    assert rank_mod_p(np.array([[p, 0], [0, 1]]), p) == 1


def test_jets_match_symbolic_lie_derivatives():
    """Taylor-mode rows = gradients of symbolic L_f^j h / j!, at a float point (P reading, k=1)."""
    s = vehicle_landmark_system("unicycle", 1, 0, 0, "unknown", "polynomial", 1)
    J = 3
    prog, _ = __import__("topomap.observability.analysis", fromlist=["_program"])._program(s)
    field = jets.Real()
    point = jets.sample_point(prog, field, np.random.default_rng(3), 1, J)
    rows, values = jets.lie_rows(prog, field, point, J)
    derivs = lie_derivatives(s.outputs, s.states, s.drift, J)
    subs = {st: float(v) for st, v in zip(s.states, point.states)}
    subs.update({pp: float(v) for pp, v in zip(s.params, point.params)})
    n = s.dimension
    for j in range(J + 1):
        grad = [float(sp.diff(derivs[j], x).subs(subs)) for x in s.states]
        np.testing.assert_allclose(rows[j, 0, 0] * math.factorial(j), grad, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(values[j, 0, 0] * math.factorial(j), float(derivs[j].subs(subs)), rtol=1e-9)
    assert rows.shape == (J + 1, 1, 1, n)


@pytest.mark.parametrize(
    "args, depth",
    [
        (("unicycle", 0, 0, 1, "known"), 6),
        (("omni", 2, 0, 0, "unknown", "analytic", 1), 2),
        (("unicycle", 1, 0, 1, "unknown", "polynomial", 0), 8),
    ],
)
def test_table_cells_agree_with_an_independent_symbolic_computation(args, depth):
    system = vehicle_landmark_system(*args)
    assert analyze(system, directions=False).unobservable_dimension == system.dimension - symbolic_rank(system, depth)


def test_float_baseline_agrees_at_low_order():
    system = vehicle_landmark_system("unicycle", 1, 0, 0, "unknown", "analytic", 1)
    assert float_rank(system) == analyze(system, directions=False).rank


def test_unsupported_expression_is_a_config_error():
    x = sp.Symbol("x")
    with pytest.raises(ConfigError, match="not supported"):
        analyze(System("exp", (x,), (sp.exp(x),), (x,)))


# ----------------------------------------------------------------------------- directions
def _readings(rep):
    return [(d.kind, d.reading) for d in rep.directions]


def test_one_marker_known_inputs_is_the_rotation_about_the_marker():
    rep = analyze(vehicle_landmark_system("unicycle", 1, 0, 0, "known"))
    assert _readings(rep) == [(DirectionKind.ROTATION, "rotation of the scene about marker m1")]
    assert {k: str(v) for k, v in rep.directions[0].field} == {"x": "-z + z_m1", "z": "x - x_m1", "theta": "1"}


def test_one_target_known_inputs_is_rotation_and_translations():
    rep = analyze(vehicle_landmark_system("omni", 0, 1, 0, "known"))
    kinds = sorted(d.kind.value for d in rep.directions)
    assert kinds == ["rotation", "translation", "translation"]


def test_half_marker_half_target_known_inputs():
    rep = analyze(vehicle_landmark_system("unicycle", 0, 0, 1, "known"))
    assert _readings(rep) == [
        (DirectionKind.ROTATION, "rotation of the scene about half marker h1"),
        (DirectionKind.TRANSLATION, "translation of the scene along z"),
    ]


def test_unknown_inputs_add_the_scale_and_input_directions():
    rep = analyze(vehicle_landmark_system("unicycle", 1, 0, 0, "unknown", "analytic", 0))
    assert [d.kind for d in rep.directions] == [DirectionKind.ROTATION, DirectionKind.SCALE, DirectionKind.INPUT]
    scale = {k: str(v) for k, v in rep.directions[1].field}
    assert scale == {"x": "x - x_m1", "z": "z - z_m1", "d_f": "d_f"}  # linear velocity scales, d_w does not
    assert set(rep.directions[2].support) <= {"d_f", "d_w"}


def test_symmetry_fields_annihilate_the_symbolic_codistribution():
    """The accepted rotation and scale fields are in the kernel of d h, d L_f h, d L_f^2 h identically."""
    s = vehicle_landmark_system("unicycle", 1, 0, 0, "unknown", "polynomial", 1)
    rep = analyze(s)
    fields = {d.kind: d for d in rep.directions if d.field}
    assert set(fields) == {DirectionKind.ROTATION, DirectionKind.SCALE}
    derivs = lie_derivatives(s.outputs, s.states, s.drift, 2)
    for d in fields.values():
        comp = dict(d.field)
        v = [comp.get(str(x), sp.Integer(0)) for x in s.states]
        for L in derivs:
            assert sp.simplify(sum(sp.diff(L, x) * vi for x, vi in zip(s.states, v))) == 0


def test_scale_is_not_accepted_with_known_inputs():
    rep = analyze(vehicle_landmark_system("unicycle", 1, 0, 0, "known"))
    assert DirectionKind.SCALE not in {d.kind for d in rep.directions}


def test_observable_system_has_no_direction():
    rep = analyze(vehicle_landmark_system("omni", 3, 0, 0, "unknown", "analytic", 2))
    assert rep.observable and rep.directions == ()


# ----------------------------------------------------------------------------- validation and table
@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(vehicle="car"), "unknown vehicle"),
        (dict(inputs="maybe"), "unknown inputs"),
        (dict(reading="x"), "unknown reading"),
        (dict(order=-1), "order"),
        (dict(order=99), "order"),
        (dict(markers=0, targets=0, half_markers=0), "no landmark"),
        (dict(markers=-1), "non-negative"),
        (dict(markers=7), "more than"),
    ],
)
def test_bad_values_raise_config_error(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        vehicle_landmark_system(**kwargs)


def test_linear_system_rejects_non_numbers():
    with pytest.raises(ConfigError, match="not a number"):
        linear_system("abc", 1, 1)


def test_table_subset_and_cache(tmp_path):
    rows = observability_table(["unicycle"], orders=2, configurations=["1 marker"], cache_dir=tmp_path)
    (row,) = rows
    assert (row.known, row.analytic, row.polynomial) == (1, (3, 4), (2, 2))
    assert row.dimensions == (3, 5, 7) and row.confirmed
    cached = list(tmp_path.glob("*.json"))
    assert len(cached) == 1 and len(json.loads(cached[0].read_text())) == 5
    assert observability_table(["unicycle"], orders=2, configurations=["1 marker"], cache_dir=tmp_path) == rows
    with pytest.raises(ConfigError, match="unknown configuration"):
        observability_table(configurations=["4 markers"])


# ----------------------------------------------------------------------------- observer
@pytest.mark.parametrize("vehicle", ["unicycle", "omni"])
def test_observer_converges_with_three_markers(vehicle):
    sim = simulate(vehicle, 3, 0, 0, "unknown", ObserverConfig(duration_s=6.0))
    rel = sim.relative_error()
    after = sim.t >= CONVERGENCE_TIME_S
    assert rel[0] == pytest.approx(1.0)
    assert np.all(rel[after] < 0.05), rel[after].max()
    assert sim.settling_time() is not None and sim.settling_time() <= CONVERGENCE_TIME_S
    assert np.max(sim.unobservable_error) < 1e-8  # J has full rank: nothing unobservable


def test_observer_does_not_recover_the_rotation_about_a_single_marker():
    for inputs in ("unknown", "known"):
        sim = simulate("unicycle", 1, 0, 0, inputs, ObserverConfig(duration_s=6.0))
        rot = np.abs(sim.rotation_error)
        assert rot[0] > 0.02
        assert rot[-1] > 0.5 * rot[0], inputs  # no convergence along the unobservable rotation
        assert sim.settling_time() is None
        assert sim.unobservable_error[-1] > 0.05


def test_observer_config_validation():
    with pytest.raises(ConfigError):
        ObserverConfig(dt_s=0.1, epsilon_s=0.02)
    with pytest.raises(ConfigError):
        ObserverConfig(order=5)
    with pytest.raises(ConfigError, match="no landmark"):
        simulate("unicycle", 0, 0, 0)
    with pytest.raises(ConfigError, match="more than"):
        simulate("unicycle", 6, 1, 0)


# ----------------------------------------------------------------------------- CLI
def test_cli_single_row_json(runner, cli_app):
    res = runner.invoke(cli_app, ["observability", "--vehicle", "unicycle", "--markers", "1", "--targets", "0",
                                  "--half-markers", "0", "--inputs", "unknown", "--reading", "analytic",
                                  "--order", "2", "--json"])
    assert res.exit_code == 0, res.output
    data = json.loads(res.stdout)
    assert {"state_dimension", "rank", "unobservable_dimension", "directions"} <= set(data)
    assert (data["state_dimension"], data["rank"], data["unobservable_dimension"]) == (9, 4, 5)
    assert data["directions"][0]["kind"] == "rotation"


def test_cli_text_output(runner, cli_app):
    res = runner.invoke(cli_app, ["observability", "--markers", "1", "--inputs", "known"])
    assert res.exit_code == 0, res.output
    assert "unobservable dimension  1" in res.stdout and "rotation of the scene about marker m1" in res.stdout


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--vehicle", "car"], "unknown vehicle"),
        (["--reading", "Q"], "unknown reading"),
        (["--inputs", "x"], "unknown inputs"),
        (["--markers", "x"], "--markers"),
        (["--order", "-1"], "order"),
    ],
)
def test_cli_bad_option_is_one_line_exit_1(runner, cli_app, args, needle):
    res = runner.invoke(cli_app, ["observability", *args])
    assert res.exit_code == 1
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and needle in lines[0] and lines[0].startswith("Error:")


def test_cli_simulate_writes_png(runner, cli_app, tmp_path):
    out = tmp_path / "err.png"
    res = runner.invoke(cli_app, ["observability", "simulate", "--markers", "3", "--inputs", "unknown",
                                  "--duration", "2", "--out", str(out), "--json"])
    assert res.exit_code == 0, res.output
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    data = json.loads(res.stdout)
    assert data["png"] == str(out) and data["settling_time_s"] is not None and data["settling_time_s"] < 2
