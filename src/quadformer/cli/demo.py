"""``quadformer demo``: the demo profile end to end, detection then resilience."""

from __future__ import annotations

import time
from pathlib import Path

import typer

from quadformer.cli.common import method_names
from quadformer.cli.tables import print_resilience, print_tables


def demo(
    out: Path = typer.Option(Path("runs/demo"), "--out", help="Output directory."),
    cache: Path = typer.Option(Path("runs/cache"), help="Dataset and tuned-model cache directory."),
    quiet: bool = typer.Option(False, help="No progress bars."),
) -> None:
    """The demo profile end to end: simulate, residues, every detector, tables, report; then a
    short resilience run over four of the configurations (QUADFormer driving the resilient
    estimator, beside the other policies)."""
    from quadformer.experiments.demo import plan, run_demo_profile
    from quadformer.experiments.grid import PROFILES, summary_table
    from quadformer.io import set_threads

    t0 = time.perf_counter()
    set_threads()
    methods = method_names(None)
    todo = plan(PROFILES["demo"], methods, cache, resilience=True)
    typer.echo(todo.describe())
    run = run_demo_profile(out, cache, methods, "demo", "quadformer", progress=not quiet, todo=todo)
    typer.echo("Datasets (GPS noise moments: velocity error on clean steps, std set to 0.1 m/s):")
    typer.echo(summary_table(run.datasets).to_string(index=False))
    print_tables(run.detection)
    print_resilience(run.resilience)
    typer.echo(f"\ndemo took {time.perf_counter() - t0:.0f} s (estimated {todo.estimate_s:.0f} s): "
               + ", ".join(f"{k} {v:.0f} s" for k, v in run.phases.items()))
    typer.echo(f"detection results: {(out / 'detection' / 'results.json').resolve()}")
    typer.echo(f"detection report:  {(out / 'detection' / 'report.html').resolve()}  (open in a browser; works offline)")
    typer.echo(f"resilience report: {(out / 'resilience' / 'report.html').resolve()}")
    typer.echo(f"alerts:            {(out / 'resilience' / 'alerts.csv').resolve()}")
