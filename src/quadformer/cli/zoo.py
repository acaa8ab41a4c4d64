"""``quadformer zoo``: the shipped detectors (list, show a model card, rebuild them)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from quadformer.cli.common import fail


def zoo_list() -> None:
    """The shipped detectors by sensor set, with their test F1 and the default of each set."""
    from quadformer.detectors import pretrained

    try:
        sets, entries = pretrained.sets(), pretrained.entries()
    except pretrained.ZooError as e:
        fail(str(e))
    for s in sets.values():
        typer.echo(f"{s.name}: {s.sensors}, {s.residues} residues"
                   + (f", {'/'.join(s.formats)} logs" if s.formats else "") + f" (default {s.default})")
        typer.echo(f"  {s.about}")
        for e in entries.values():
            if e.set.name != s.name:
                continue
            t = e.card["test"]
            f1, b = t["at_f1_threshold"], t["at_budget_threshold"]
            typer.echo(f"  {e.name:22s} test F1 {f1['f1']:.2f} [{_ci(f1)}]; at the budget threshold F1 {b['f1']:.2f}, "
                       f"{_num(b['false_alarms_per_hour'])} false alarms per clean flight-hour "
                       f"({t['flights']} simulated test flights)")
    typer.echo("`quadformer zoo show NAME` for a model card; `quadformer detect LOG` picks the set that fits the log.")


def zoo_show(
    name: str = typer.Argument(..., help="A shipped detector's name, or a sensor set (its default)."),
    as_json: bool = typer.Option(False, "--json", help="The whole card as JSON."),
) -> None:
    """A shipped detector's model card: training data and seeds, sensors and rates, calibration,
    figures on held-out simulated flights, package versions, checksums."""
    from quadformer.detectors import pretrained

    try:
        e = pretrained.verify(name)
    except pretrained.ZooError as err:
        fail(str(err))
    c = e.card
    if as_json:
        typer.echo(json.dumps({"name": e.name, "files": e.files, "card": c}, indent=2))
        return
    tr = c["training"]
    typer.echo(f"{e.name}: {c['method']} for {c['sensors']} ({c['residues']} residues)")
    typer.echo(f"  {c['about']}")
    typer.echo("training data (simulated; no real log):")
    for s in tr["simulation"]:
        a = s["attack"]
        typer.echo(f"  {s['config']}: Model {s['model']}, {s['noise']} noise, {s['flights']} flights x "
                   f"{s['duration_s']:g} s, seed {s['seed']}, attack {a['kind']}"
                   + (f" ({'/'.join(a['mix'])})" if a.get("mix") else "")
                   + (f", offset {a['magnitude_m']} m" if a.get("magnitude_m") else "")
                   + (f", drift {a['rate_m_s']} m/s" if a.get("rate_m_s") else ""))
    sp = tr["split"]
    typer.echo(f"  split {sp['rule']} (seed {sp['split_seed']}): {sp['train']} train ({sp['labelled']} labelled), "
               f"{sp['val']} validation, {sp['test']} test flights")
    typer.echo(f"  tuned: {tr['params']} (validation F1 {tr['validation_f1']:.3f}; {tr['budget']}; "
               f"{tr['threads']} threads)")
    typer.echo("rates: " + ", ".join(f"{k.removesuffix('_hz')} {v:g} Hz" for k, v in c["rates"].items()))
    cal = c["calibration"]
    typer.echo(f"calibration: F1 threshold {cal['f1_threshold']:.4g}; budget threshold {_num(cal['budget_threshold'])} "
               f"({cal['budget_per_hour']:g} false alarm per clean flight-hour on the validation flights; the "
               "threshold `detect` and `monitor` use)")
    t = c["test"]
    typer.echo(f"test: {t['flights']} held-out simulated flights ({t['attacked_flights']} attacked, "
               f"{t['flight_hours']:.2f} flight-hours)")
    for label, key in (("at the F1 threshold", "at_f1_threshold"), ("at the budget threshold", "at_budget_threshold")):
        f = t[key]
        typer.echo(f"  {label}: F1 {f['f1']:.3f} [{_ci(f)}], precision {f['precision']:.3f}, recall {f['recall']:.3f}, "
                   f"event recall {_num(f['event_recall'])}, median delay {_num(f['delay_median_s'])} s, "
                   f"{_num(f['false_alarms_per_hour'])} false alarms per clean flight-hour")
        typer.echo("    per configuration F1: " + ", ".join(f"{k} {v:.2f}" for k, v in f["per_config_f1"].items()))
    if c.get("paper_profile"):
        pp = c["paper_profile"]
        typer.echo(f"paper profile, same method ({pp['source']}): F1 "
                   + ", ".join(f"{k} {v:.2f}" for k, v in pp["f1"].items()))
    fd = c.get("field")
    if fd:
        typer.echo(f"field benchmark on real flights ({fd['source']}; {fd['logs_read']} logs replayed, "
                   f"{fd['logs_refused']} refused):")
        for r in fd["false_alarms_clean"]:
            typer.echo(f"  {r['threshold']} threshold: {r['spoofing_air']} spoofing alert(s) in {r['air_hours']:.3f} "
                       f"in-air hours of clean flights = {r['per_air_hour']:.0f} per hour [{r['ci_low']:.0f}, "
                       f"{r['ci_high']:.0f}]")
        for r in fd["injected"]:
            typer.echo(f"  {r['threshold']} threshold, injected {r['kind']}: event recall {_num(r['event_recall'])} "
                       f"({r['injected']} injected), median delay {_num(r['delay_median_s'])} s")
        if fd["unscored"]:
            typer.echo(f"  not scored on {len(fd['unscored'])} log(s): {fd['unscored'][0]['reason']}")
    else:
        typer.echo("field benchmark: not run on this detector (`quadformer benchmark --profile field --shipped SET`)")
    typer.echo("versions: " + ", ".join(f"{k} {v}" for k, v in c["versions"].items()))
    typer.echo("files (SHA-256, checked): " + ", ".join(f"{f} {d[:16]}" for f, d in e.files.items()))


def zoo_build(
    out: Optional[Path] = typer.Option(None, "--out", help="Directory to write (default: the package's shipped "
                                       "detectors, replaced once everything is written)."),
    cache: Path = typer.Option(Path("runs/cache"), help="Dataset cache directory."),
    sets: Optional[str] = typer.Option(None, help="Comma-separated sets to build (default: all)."),
    methods: Optional[str] = typer.Option(None, help="Comma-separated methods to rebuild in --sets, keeping the "
                                          "sets' other detectors (built from the same flights)."),
    flights: Optional[int] = typer.Option(None, help="Flights per configuration (default: each recipe's)."),
    seed: Optional[int] = typer.Option(None, help="The zoo's seed (default 1000; the benchmarks test on 0-99, "
                                       "the demo on 2000)."),
    field: Optional[Path] = typer.Option(None, help="A field run's results.json on a shipped set (`quadformer "
                                         "benchmark --profile field --shipped SET`): its figures go into the set's "
                                         "cards when it judged the very files built (same checksums)."),
    quiet: bool = typer.Option(False, help="No progress bars."),
) -> None:
    """Rebuild the shipped detectors from their recipes: simulate, tune and calibrate every method,
    score held-out flights, write the detectors, their checksums and cards. Same machine, same seed:
    same files."""
    from quadformer.experiments.zoo import ZOO_SEED, build

    try:
        doc = build(out, cache, sets=[s.strip() for s in sets.split(",")] if sets else None, flights=flights,
                    seed=ZOO_SEED if seed is None else seed, progress=not quiet, echo=typer.echo, field=field,
                    methods=[m.strip() for m in methods.split(",") if m.strip()] if methods is not None else None)
    except ValueError as e:
        fail(str(e))
    except OSError as e:      # an installed package's folder may not be writable
        fail(f"cannot write the detectors: {e}; build them elsewhere with --out DIR")
    from quadformer.detectors import pretrained

    where = out or pretrained.ROOT
    typer.echo(f"wrote {len(doc['detectors'])} detectors to {Path(where).resolve()} in {doc['build_seconds']:.0f} s")
    for name, d in doc["detectors"].items():
        typer.echo(f"  {name}: " + ", ".join(f"{f} {h[:16]}" for f, h in d["files"].items()))


def _ci(f: dict) -> str:
    ci = f.get("f1_ci95")
    return f"{ci[0]:.2f}, {ci[1]:.2f}" if ci else "-"


def _num(x) -> str:
    return "-" if x is None or x != x else f"{x:.3g}"
