"""The console's tables: benchmark results in the paper's layout, attack typing, stress sets,
seeds and the resilience policies (formatting only; the tables come from ``quadformer.report``)."""

from __future__ import annotations

import typer


def print_tables(results: dict) -> None:
    from quadformer.report import dataset_table, paper_tables

    if results.get("profile") is None:
        df = dataset_table(results)
        typer.echo("\nPoint-wise P / R / F1 on test flights")
        flat = df.copy()
        flat.columns = [f"{d}-{m}" for d, m in df.columns]
        typer.echo(flat.to_string(float_format=lambda v: f"{v:.2f}"))
        return
    for key, df in paper_tables(results).items():
        typer.echo(f"\nModel {key.split('_')[1]}: point-wise P / R / F1 on test flights")
        flat = df.copy()
        flat.columns = [f"{n[:3]}-{a.split('(')[1].rstrip(')')}-{m}" for n, a, m in df.columns]
        typer.echo(flat.to_string(float_format=lambda v: f"{v:.2f}"))
    print_typing(results)
    print_stress(results)


def print_typing(results: dict) -> None:
    from quadformer.report.detection_tables import typing_table

    df = typing_table(results)
    if df is not None:
        typer.echo("\nAttacks typed right, of the detected attacks on test flights (shape typer: no labels)")
        typer.echo(df.to_string())


def print_stress(results: dict) -> None:
    from quadformer.report.detection_tables import stress_table

    df = stress_table(results)
    if df is None:
        return
    typer.echo(f"\nStress sets ({results['stress']['flights_per_set']} flights each, half attacked; detectors "
               "tuned as above, thresholds from validation flights: of best F1, and at the false-alarm budget), "
               "pooled over configurations:")
    cols = ["stress set", "method", "event recall", "delay median (s)", "FA/h (clean flights)", "F1 (point-wise)",
            "budget: event recall", "budget: delay median (s)", "budget: FA/h (clean flights)"]
    flat = df[cols].rename(columns={"delay median (s)": "delay (s)", "FA/h (clean flights)": "FA/h",
                                    "F1 (point-wise)": "F1", "budget: event recall": "| budget: event recall",
                                    "budget: delay median (s)": "delay (s)", "budget: FA/h (clean flights)": "FA/h"})
    typer.echo(flat.to_string(index=False, na_rep="-", float_format=lambda v: f"{v:.2f}"))


def print_seeds(results: dict) -> None:
    from quadformer.report.detection_seeds import seeds_table

    typer.echo(f"\nPoint-wise F1 on test flights over seeds {', '.join(map(str, results['seeds']))}: "
               "mean ± std [min, max]")
    typer.echo(seeds_table(results, "f1").to_string())


def print_resilience(results: dict) -> None:
    from quadformer.report import overall_table

    typer.echo(f"\nResilience, detector {results['detector']}, all configurations (test flights flown again "
               "under each policy):")
    typer.echo(overall_table(results).to_string(index=False, na_rep="-", float_format=lambda v: f"{v:.2f}"))
    typer.echo("exclusion P / R / F1: every GPS step a prediction, GPS excluded, against GPS spoofed (point-wise)")
    n = sum(c.get("alerts", 0) for c in results["configs"])
    typer.echo(f"{n} alert(s) raised on the resilient flights (start, estimated onset, type, peak score, end, "
               "type confirmed 5 s later) in alerts.csv")


def print_field(results: dict) -> None:
    """The field benchmark's tables: false alarms on clean flights, injected spoofs, GPS trouble."""
    import pandas as pd

    fmt = {"float_format": lambda v: f"{v:.2f}", "index": False}
    fa = pd.DataFrame(results["false_alarms"])
    typer.echo(f"\n{len(results['read'])} logs read, {len(results['refused'])} refused")
    for r in results["refused"]:
        typer.echo(f"  refused {r['log']}: {r['reason']}")
    if len(fa):
        typer.echo("\nClean flights: spoofing alerts in air per in-air hour (95% Poisson interval); ground, "
                   "transition and degraded alerts apart")
        typer.echo(fa.to_string(**fmt))
    inj = pd.DataFrame(results["injection"])
    if len(inj):
        typer.echo("\nSpoofs injected in air (recall_big: offsets >= 2 m, drifts >= 0.2 m/s)")
        typer.echo(inj.to_string(**fmt))
    tr = pd.DataFrame(results.get("troubles", []))
    if len(tr):
        typer.echo("\nLogs with GPS trouble: alerts inside the manifest's windows by kind, spoofing alerts outside")
        typer.echo(tr.to_string(**fmt))
    rec = results.get("receiver", [])
    if rec:
        covered = sum(r["covered"] for r in rec)
        typer.echo(f"\nReceiver signs of trouble with a degraded alert within 2 s: {covered} of {len(rec)}")
