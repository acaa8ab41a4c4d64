"""``quadformer demo``: the shipped detectors on new flights (detection, resilience, logs), or with
``--train`` the demo profile trained from scratch."""

from __future__ import annotations

import time
from pathlib import Path

import typer

from quadformer.cli.common import fail, method_names
from quadformer.cli.tables import print_resilience, print_tables


def demo(
    out: Path = typer.Option(Path("runs/demo"), "--out", help="Output directory."),
    cache: Path = typer.Option(Path("runs/cache"), help="Dataset and tuned-model cache directory."),
    train: bool = typer.Option(False, "--train", help="Train every default detector from scratch on the demo "
                               "profile (at an eighth of the training budget, about 4 minutes) instead of "
                               "scoring with the shipped ones."),
    quiet: bool = typer.Option(False, help="No progress bars."),
) -> None:
    """What the tool does, in a few minutes: the shipped detectors score 160 new simulated flights of the
    paper's eight configurations (comparison tables, report), QUADFormer's drives the resilient estimator
    on four of them, and `detect` reads two simulated flights written as PX4 and ArduPilot logs. With
    --train: simulate, tune every default detector, tables, report, resilience."""
    from quadformer.io import set_threads

    set_threads()
    if train:
        _trained(out, cache, quiet)
    else:
        _shipped(out, cache, quiet)


def _shipped(out: Path, cache: Path, quiet: bool) -> None:
    from quadformer.detectors import pretrained
    from quadformer.detectors.alarms import alert_counts
    from quadformer.experiments.demo import DRIFT_RATE, SHIPPED_FLY, run_shipped_demo, shipped_profile, versus_paper
    from quadformer.experiments.grid import summary_table
    from quadformer.experiments.zoo import ZOO_SEED

    t0 = time.perf_counter()
    prof = shipped_profile()
    try:
        entries = pretrained.entries()
    except pretrained.ZooError as e:
        fail(str(e))
    vio = [e for e in entries.values() if e.set.name == "vio"]
    if not vio:
        fail("no shipped detector of the vio set; `quadformer zoo build --sets vio`, or `quadformer demo --train`")
    card = vio[0].card["training"]
    n_train = sum(s["flights"] for s in card["simulation"])
    typer.echo(f"Shipped detectors, no training here: {', '.join(e.name for e in vio)}, pretrained on {n_train} "
               f"simulated flights of the paper's eight configurations (seed {ZOO_SEED}; `quadformer zoo show NAME`).")
    typer.echo(f"Test flights: {prof.flights} new flights per configuration (seed {prof.seed}), none of which "
               "a shipped detector saw; thresholds are the shipped ones (best F1 on the zoo's validation flights; "
               "the budget ones in the `budget:` columns). About 3 minutes on 2 cores.")
    try:
        run = run_shipped_demo(out, cache, progress=not quiet)
    except (ValueError, pretrained.ZooError) as e:
        fail(str(e))
    typer.echo("Test datasets (GPS noise moments: velocity error on clean steps):")
    typer.echo(summary_table(run.datasets).to_string(index=False))
    print_tables(run.detection)
    rows = versus_paper(run.detection)
    if rows:
        typer.echo(f"\n{run.shipped['quadformer']} on these new flights (test F1, 95% bootstrap interval over flights) "
                   "beside the paper profile's QUADFormer (a model per configuration, 360 training flights each; "
                   "docs/results.md):")
        for r in rows:
            ci = f"[{r['ci95'][0]:.2f}, {r['ci95'][1]:.2f}]" if r["ci95"] else "[-]"
            typer.echo(f"  {r['config']:26s} {r['f1']:.2f} {ci}  paper {r['paper']:.2f}"
                       + ("  (inside)" if r["holds"] else "  (outside)"))
        typer.echo(f"  the paper's figure inside the interval in {sum(r['holds'] for r in rows)} of {len(rows)}")
    typer.echo(f"\nResilience: {run.shipped['quadformer']} driving the resilient estimator, the first {SHIPPED_FLY} "
               "test flights of four configurations flown again under each GPS policy:")
    print_resilience(run.resilience)
    typer.echo(f"\n`quadformer detect` on simulated flights of a vehicle without a camera (GPS, IMU, compass, "
               f"barometer), each written as a PX4 ULog and an ArduPilot DataFlash log: flight_0000/0001 with the "
               f"fleet's noise (one under a bias), drift_0000 under a consistent drift of {DRIFT_RATE:g} m/s switched "
               f"on at once (position and velocity agree; each attack in the .attack.json beside its logs); no "
               f"--model: the shipped {run.log_detector}")
    for o in run.logs.outcomes:
        if o.status == "scored":
            n = alert_counts(o.detection.alerts)
            first = next((a for a in o.detection.alerts if a.kind == "spoofing" and a.phase == "air"), None)
            typer.echo(f"  {o.path.name}: {n['alerts']} spoofing alert(s) in the air"
                       + (f", the first raised at {first.start_s:.1f} s, onset estimated {first.onset_s:.1f} s "
                          f"({_typed(first)})" if first is not None else ""))
        else:
            typer.echo(f"  {o.path.name}: {o.status}: {o.reason}")
    typer.echo(f"\ndemo took {time.perf_counter() - t0:.0f} s: " + ", ".join(f"{k} {v:.0f} s"
                                                                      for k, v in run.phases.items()))
    typer.echo(f"detection report:  {(out / 'detection' / 'report.html').resolve()}  (open in a browser; "
               "works offline)")
    typer.echo(f"resilience report: {(out / 'resilience' / 'report.html').resolve()}")
    typer.echo(f"log reports:       {(out / 'logs').resolve()}/*/report.html")
    typer.echo("Train every method from scratch instead: quadformer demo --train")


def _trained(out: Path, cache: Path, quiet: bool) -> None:
    from quadformer.experiments.demo import plan, run_demo_profile
    from quadformer.experiments.grid import PROFILES, summary_table

    t0 = time.perf_counter()
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
    typer.echo(f"detection report:  {(out / 'detection' / 'report.html').resolve()}  (open in a browser; "
               "works offline)")
    typer.echo(f"resilience report: {(out / 'resilience' / 'report.html').resolve()}")
    typer.echo(f"alerts:            {(out / 'resilience' / 'alerts.csv').resolve()}")


def _typed(alert) -> str:
    """An alert's type as the demo prints it: the type confirmed 5 s after the alarm (the one to
    trust), with the first guess beside it where they differ."""
    if alert.confirmed_type is None or alert.confirmed_type == alert.attack_type:
        return alert.attack_type
    return f"{alert.confirmed_type}; at the alarm {alert.attack_type}"
