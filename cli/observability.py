"""``topomap observability``: exact observability analysis, the thesis' table, and the observer demo."""

from __future__ import annotations

import time
from pathlib import Path

import typer
from rich import box
from rich.markup import escape
from rich.table import Table

from topomap.observability import (
    analyze,
    default_cache_dir,
    observability_table,
    vehicle_landmark_system,
)
from topomap.observability.observer import ObserverConfig, plot_simulation, simulate
from topomap_cli.app import app, console, fail, print_json

obs_app = typer.Typer(
    help="What can be recovered from bearings alone (docs/theory.md section 2), and an observer that recovers it.",
    no_args_is_help=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)
app.add_typer(obs_app, name="observability")

_VEHICLE = typer.Option("unicycle", "--vehicle", help="unicycle | omni")
_MARKERS_HELP = "Landmarks with known position."
_TARGETS_HELP = "Landmarks with unknown position."
_HALF_HELP = "Landmarks with one known coordinate (x)."
_INPUTS = typer.Option("unknown", "--inputs", help="known (odometry) | unknown (appearance only: u + d unknown)")


@obs_app.callback(invoke_without_command=True)
def observability(
    ctx: typer.Context,
    vehicle: str = _VEHICLE,
    markers: int = typer.Option(1, "--markers", help=_MARKERS_HELP),
    targets: int = typer.Option(0, "--targets", help=_TARGETS_HELP),
    half_markers: int = typer.Option(0, "--half-markers", help=_HALF_HELP),
    inputs: str = _INPUTS,
    reading: str = typer.Option("analytic", "--reading", help="analytic (A: d^(k+1) unknown) | polynomial (P: d^(k+1) = 0)"),
    order: int = typer.Option(0, "--order", "-k", help="Augmentation order k of the unknown inputs."),
    table: bool = typer.Option(False, "--table", help="Print the thesis' table instead (all configurations, both vehicles)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the random evaluation points."),
    workers: int = typer.Option(1, "--workers", help="Processes for --table."),
    cache: bool = typer.Option(False, "--cache/--no-cache", help="Reuse --table cells from the user cache directory."),
    json_out: bool = typer.Option(False, "--json", help="Machine-readable output."),
) -> None:
    """Rank of the observability codistribution (exact), unobservable dimension and directions.

    Examples: `topomap observability --markers 1 --inputs unknown --reading analytic --order 2`,
    `topomap observability --table`, `topomap observability simulate --markers 3`.
    """
    if ctx.invoked_subcommand is not None:
        return
    if table:
        _table(seed=seed, workers=workers, cache=cache, json_out=json_out)
        return
    system = vehicle_landmark_system(vehicle, markers, targets, half_markers, inputs, reading, order)
    report = analyze(system, seed=seed)
    if json_out:
        print_json(report.to_dict())
        return
    console.print(f"[bold]{report.name}[/]")
    console.print(f"state ({report.state_dimension}): {', '.join(report.state_names)}")
    console.print(f"state dimension         {report.state_dimension}")
    check = "confirmed" if report.confirmed else "[yellow]NOT confirmed[/]"
    console.print(
        f"rank                    {report.rank}  (exact over GF(p) at two random points: "
        f"{report.ranks[0]}, {report.ranks[1]}, {check}; derivatives up to order {report.derivative_order})"
    )
    console.print(f"unobservable dimension  {report.unobservable_dimension}")
    if report.directions:
        console.print("unobservable directions:")
        for i, d in enumerate(report.directions, 1):
            extra = ""
            if d.field:
                extra = "  [dim](" + escape(", ".join(f"δ{k} = {v}" for k, v in d.field)) + ")[/]"
            console.print(f"  {i}. {escape(f'[{d.kind.value}]')} {escape(d.reading)}{extra}", markup=True)
    else:
        console.print("locally weakly observable: no unobservable direction")


def _table(*, seed: int, workers: int, cache: bool, json_out: bool) -> None:
    if workers < 1:
        fail(f"--workers {workers} must be at least 1")
    t0 = time.perf_counter()
    rows = observability_table(seed=seed, workers=workers, cache_dir=default_cache_dir() if cache else None)
    seconds = time.perf_counter() - t0
    if json_out:
        print_json({"rows": [r.to_dict() for r in rows], "orders": list(range(len(rows[0].analytic))),
                    "seconds": round(seconds, 2)})
        return
    orders = range(len(rows[0].analytic))
    for vehicle in dict.fromkeys(r.vehicle for r in rows):
        t = Table(title=f"unobservable dimension — {vehicle.value}", title_justify="left", box=box.SIMPLE_HEAD)
        t.add_column("configuration", no_wrap=True)
        t.add_column("dim", justify="right")
        t.add_column("USO", justify="right", min_width=3)
        for k in orders:
            t.add_column(f"A{k}", justify="right")
        for k in orders:
            t.add_column(f"P{k}", justify="right")
        for r in (r for r in rows if r.vehicle is vehicle):
            flag = "" if r.confirmed else " (!)"
            t.add_row(r.configuration + flag, str(r.dimensions[0]), str(r.known),
                      *(str(v) for v in r.analytic), *(str(v) for v in r.polynomial))
        console.print(t)
    console.print(
        "dim: state dimension without inputs; USO: known inputs; Ak / Pk: unknown inputs under reading (A)"
        " analytic / (P) polynomial, augmented to order k (dimension dim + channels x (k + 1)). Exact ranks over"
        f" GF(p) at two points each{'' if all(r.confirmed for r in rows) else '; (!) the two points disagreed'}."
        f" {seconds:.1f} s"
    )


@obs_app.command("simulate")
def simulate_cmd(
    vehicle: str = _VEHICLE,
    markers: int = typer.Option(3, "--markers", help=_MARKERS_HELP),
    targets: int = typer.Option(0, "--targets", help=_TARGETS_HELP),
    half_markers: int = typer.Option(0, "--half-markers", help=_HALF_HELP),
    inputs: str = _INPUTS,
    order: int = typer.Option(1, "--order", "-k", help="Augmentation order k of the observer (reading A)."),
    duration: float = typer.Option(10.0, "--duration", help="Simulated time [s]."),
    gain: float = typer.Option(8.0, "--gain", help="Observer gain Gamma [1/s]."),
    epsilon: float = typer.Option(0.02, "--epsilon", help="High-gain differentiator time scale [s]."),
    seed: int = typer.Option(0, "--seed", help="Seed of the initial estimation errors."),
    out: Path = typer.Option(Path("observer_errors.png"), "--out", "-o", help="PNG of the estimation errors."),
    json_out: bool = typer.Option(False, "--json", help="Machine-readable summary."),
) -> None:
    """Run the unknown-input observer against a simulated vehicle and plot its estimation errors."""
    config = ObserverConfig(order=order, duration_s=duration, gain_per_s=gain, epsilon_s=epsilon,
                            dt_s=min(1e-3, epsilon / 4), seed=seed)
    sim = simulate(vehicle, markers, targets, half_markers, inputs, config)
    png = plot_simulation(sim, out)
    summary = {**sim.summary(), "png": str(png)}
    if json_out:
        print_json(summary)
        return
    settle = summary["settling_time_s"]
    console.print(
        f"{summary['vehicle']}, {markers} marker(s), {half_markers} half marker(s), {targets} target(s), "
        f"{summary['inputs']} inputs, {summary['duration_s']:.1f} s simulated"
    )
    console.print(
        "error below 5 % of its initial size from t = "
        + (f"{settle:.2f} s" if settle is not None else "— never (some directions are unobservable)")
    )
    console.print(f"final relative error    {summary['final_relative_error']:.3g}  "
                  + ", ".join(f"{g} {v:.3g}" for g, v in summary["final_relative_error_by_group"].items()))
    console.print(f"rotation about landmark 1: {summary['rotation_error_initial_rad']:.3g} rad -> "
                  f"{summary['rotation_error_final_rad']:.3g} rad; error in ker J: {summary['unobservable_error_final']:.3g}")
    console.print(f"plot: {png}")
