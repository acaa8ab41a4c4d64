"""``quadformer benchmark``, ``fit``, ``evaluate``, ``export`` and ``resilience``: the
detection and resilience benchmarks, and one detector fitted, scored and exported."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from quadformer.cli.common import (ADDRESS_HELP, BACKEND_HELP, CONFIGS_HELP, DEVICE_HELP, MODEL_HELP, RUNTIME_HELP,
                                   STALE_HOLD_HELP, TYPING_HELP, check_backend, check_typing, fail,
                                   load_dataset_dir, load_model_file, log_paths, message, method_names, print_alerts,
                                   seed_runs, select_profile)
from quadformer.cli.tables import print_field, print_resilience, print_seeds, print_tables


def benchmark(
    profile: str = typer.Option("demo", help="demo (20 flights/config), quick (60), paper (600), mixed (60 "
                                "flights/config of mixed attacks, Model I/II x exponential/Laplace noise), or field "
                                "(detectors trained in simulation, judged on the real flight logs of --logs), or "
                                "stealth (each shipped detector against an attacker who knows it; stealth-quick: "
                                "two detectors, 30 s; --methods names shipped detectors; docs/stealth.md)."),
    methods: Optional[str] = typer.Option(None, help="Comma-separated detector names; default: every registered "
                                          "detector except ablations; 'all': every one."),
    data: list[Path] = typer.Option([], "--data", help="Benchmark on these dataset directories instead of a "
                                    "profile (repeatable): simulated ones or `quadformer logs import` ones."),
    configs: Optional[str] = typer.Option(None, help=CONFIGS_HELP),
    out: Path = typer.Option(Path("runs/benchmark"), "--out", help="Output directory."),
    cache: Path = typer.Option(Path("runs/cache"), help="Dataset cache directory."),
    seed: int = typer.Option(0, help="Split seed (with --seeds, the first seed)."),
    label_fraction: float = typer.Option(0.2, help="Share of training flights whose labels methods may use."),
    stress: bool = typer.Option(False, "--stress", help="Also score the tuned detectors on small stress datasets "
                                "outside the tuning ranges (small offsets, slow drifts, long attacks, other attack "
                                "shapes, Gaussian noise; the profile's stress_flights each, 24 on quick)."),
    seeds: Optional[int] = typer.Option(None, "--seeds", help="Run the whole protocol for N seeds (seed, seed+1, "
                                        "...): each seed its own datasets (profile seed) and split; tables of mean, "
                                        "std and min-max over seeds."),
    seed_list: Optional[str] = typer.Option(None, "--seed-list", help="Like --seeds with these seeds, e.g. 0,3,7."),
    workers: Optional[int] = typer.Option(None, help="Local worker processes (default: one per core)."),
    backend: str = typer.Option("local", help=BACKEND_HELP),
    address: Optional[str] = typer.Option(None, help=ADDRESS_HELP),
    device: str = typer.Option("auto", help=DEVICE_HELP),
    logs: list[Path] = typer.Option([], "--logs", help="Field profile: real flight logs or directories of them "
                                    "(repeatable)."),
    manifest: Optional[Path] = typer.Option(None, help="Field profile: a CSV naming the clean logs and the "
                                            "others' GPS-trouble times (docs/field.md); without it every log "
                                            "counts as clean."),
    flights: int = typer.Option(60, help="Field profile: simulated training flights."),
    injections: int = typer.Option(6, help="Field profile: spoofs of each kind injected into each clean log "
                                   "segment in air."),
    shipped: Optional[str] = typer.Option(None, help="Field profile: judge a shipped set's detectors (e.g. "
                                          "magbaro; `quadformer zoo list`) instead of tuning --methods."),
    knowledge: Optional[str] = typer.Option(None, help="Stealth profiles: the attackers to run, comma-separated, "
                                            "of white, grey, black (default: the profile's)."),
    policies: Optional[str] = typer.Option(None, help="Stealth profiles: the GPS policies flown, comma-separated, "
                                           "of none (GPS always fused: the deviation unseen) and resilient (the "
                                           "detector's alarms exclude GPS in the loop: the deviation reached)."),
    headings: Optional[int] = typer.Option(None, help="Stealth profiles: the axes the white and grey boxes search "
                                           "each GPS step (default 1: along the attack's direction; more: across "
                                           "the track too, that many times the probes)."),
    rehearse: Optional[str] = typer.Option(None, help="Stealth profiles: the plans' accelerations (m/s^2, "
                                           "comma-separated) the white and grey boxes rehearse on their own flights "
                                           "beside the fastest push, flying the one that went farthest unseen; "
                                           "'none': the fastest push, unrehearsed (default: the profile's)."),
    quiet: bool = typer.Option(False, help="No progress bars."),
) -> None:
    """Simulate (or reuse) the profile's configurations, tune and evaluate methods, write tables and a
    report. With --data, the same protocol on given datasets; with --profile field, on real logs."""
    if profile == "field" or logs or manifest is not None:
        return _field(profile, logs, manifest, methods, data, configs, out, seed, flights, injections, shipped)
    if profile.startswith("stealth"):
        return _stealth(profile, methods, data, configs, out, seed, knowledge, policies, headings, rehearse)
    if knowledge is not None or policies is not None or headings is not None or rehearse is not None:
        fail("--knowledge, --policies, --headings and --rehearse belong to the stealth profiles (--profile "
             "stealth or stealth-quick)")
    if shipped is not None:
        fail("--shipped belongs to --profile field (the demo scores the shipped detectors on simulated flights)")
    from quadformer.dataset import DatasetError
    from quadformer.experiments.detection import run_benchmark, run_datasets
    from quadformer.experiments.seeds import run_seeds
    from quadformer.experiments.pool import BackendError, UnitError
    from quadformer.io import set_threads

    if data and configs is not None:
        fail("--configs selects a profile's configurations; with --data the datasets are given")
    prof = None if data else select_profile(profile, configs)
    if not 0.0 <= label_fraction <= 1.0:
        fail(f"label-fraction: must be in [0, 1], got {label_fraction}")
    runs = seed_runs(seeds, seed_list, seed)
    if data and (stress or runs is not None):
        fail("--stress, --seeds and --seed-list need a profile (simulated datasets), not --data")
    names = method_names(methods)
    be = check_backend(backend, address, device, workers)
    if data and be.kind != "local":
        fail("--data runs in this process; --backend ray needs a profile")
    set_threads()
    try:
        if data:
            results = run_datasets(data, names, out, progress=not quiet, seed=seed, label_fraction=label_fraction,
                                   device=device)
        elif runs is not None:
            results = run_seeds(prof, names, out, cache, runs, progress=not quiet, workers=workers,
                                label_fraction=label_fraction, stress=stress, backend=be, device=device)
        else:
            results = run_benchmark(prof, names, out, cache, progress=not quiet, workers=workers, seed=seed,
                                    label_fraction=label_fraction, stress=stress, backend=be, device=device)
    except (DatasetError, ValueError, BackendError, UnitError) as e:
        fail(str(e))
    if runs is not None:
        print_seeds(results)
        typer.echo(f"\nbenchmark over {len(runs)} seeds took {results['timing_s']['total']:.0f} s; each seed's "
                   f"tables and report in {out}/seed-<s>/")
    else:
        print_tables(results)
        typer.echo(f"\nbenchmark took {results['timing_s']['total']:.0f} s "
                   f"(simulation {results['timing_s']['simulate']:.0f} s)")
    typer.echo(f"results: {(out / 'results.json').resolve()}")
    typer.echo(f"report:  {(out / 'report.html').resolve()}")


def _stealth(profile, methods, data, configs, out, seed, knowledge=None, policies=None, headings=None,
             rehearse=None) -> None:
    import dataclasses

    from quadformer.detectors import pretrained
    from quadformer.experiments.stealth import PROFILES, run_stealth
    from quadformer.io import set_threads
    from quadformer.report.stealth import resilient_table, stealth_table

    if profile not in PROFILES:
        fail(f"--profile {profile!r}; the stealth profiles are {', '.join(PROFILES)}")
    if data or configs is not None:
        fail("--profile stealth flies each shipped detector's own simulation: no --data or --configs")
    plan = PROFILES[profile]
    if methods is not None:
        names = tuple(m.strip() for m in methods.split(",") if m.strip())
        for n in names:
            try:
                pretrained.resolve(n)
            except pretrained.ZooError as e:
                fail(f"--methods: {e}")
        plan = dataclasses.replace(plan, detectors=names)
    for option, field, value in (("--knowledge", "knowledge", knowledge), ("--policies", "policies", policies)):
        if value is not None:
            try:
                plan = dataclasses.replace(plan, **{field: tuple(k.strip() for k in value.split(",") if k.strip())})
            except ValueError as e:
                fail(f"{option}: {e}")
    if rehearse is not None:
        try:
            accels = () if rehearse.strip().lower() == "none" else tuple(
                float(a) for a in rehearse.split(",") if a.strip())
            plan = dataclasses.replace(plan, rehearse=accels)
        except ValueError as e:
            fail(f"--rehearse: {e} (give accelerations in m/s^2, e.g. 0.02,0.05,0.2, or none)")
    try:
        plan = dataclasses.replace(plan, seed=seed, **({} if headings is None else {"headings": headings}))
    except ValueError as e:
        fail(f"--headings: {e}")
    set_threads(1)      # the closed loop's small batched operations and a detector's stream per probe: one
                        # thread each is fastest (two threads of each of two runs on two cores ran 5-50x slower)
    try:
        results = run_stealth(plan, out, echo=typer.echo, profile=profile)
    except ValueError as e:
        fail(str(e))
    for title, frame in (("deviation unseen (m, median / worst)", stealth_table(results)),
                         ("under the resilient GPS policy: deviation reached (m, median / worst)",
                          resilient_table(results))):
        if len(frame):
            typer.echo(f"{title}:\n{frame.to_string(index=False)}")
    typer.echo(f"results: {(out / 'results.json').resolve()}")
    typer.echo(f"report:  {(out / 'report.html').resolve()}")


def _field(profile, logs, manifest, methods, data, configs, out, seed, flights, injections, shipped) -> None:
    from quadformer.experiments.field import FieldPlan, run_field
    from quadformer.io import set_threads
    from quadformer.logs import LogError
    from quadformer.logs.manifest import ManifestError

    if profile != "field":
        fail("--logs and --manifest belong to --profile field")
    if not logs:
        fail("--profile field needs --logs LOG|DIR (repeatable): the real flights to judge the detectors on")
    if data or configs is not None:
        fail("--profile field takes --logs, not --data or --configs")
    if flights < 2 or injections < 0:
        fail(f"--flights must be >= 2 and --injections >= 0, got {flights} and {injections}")
    if manifest is not None and not manifest.is_file():
        fail(f"manifest: {manifest} is not a file")
    paths = log_paths(logs, None)
    set_threads()
    try:
        results = run_field(paths, out, FieldPlan(tuple(method_names(methods)), flights=flights, seed=seed,
                                                  injections=injections), manifest, echo=typer.echo, shipped=shipped)
    except (LogError, ManifestError, ValueError) as e:
        fail(str(e))
    print_field(results)
    typer.echo(f"results: {(out / 'results.json').resolve()}")
    typer.echo(f"report:  {(out / 'report.html').resolve()}")


def fit(
    method: str = typer.Option(..., help="Detector name."),
    data: Path = typer.Option(..., help="Dataset directory (from `quadformer simulate`)."),
    out: Path = typer.Option(..., "--out", help="Model file to write (JSON)."),
    seed: int = typer.Option(0, help="Split seed."),
    label_fraction: float = typer.Option(0.2, help="Share of training flights whose labels may be used."),
) -> None:
    """Fit and calibrate one detector on a dataset's train and validation flights."""
    from quadformer.dataset import DatasetError, load_dataset
    from quadformer.experiments.models import fit_model

    method_names(method)
    try:
        ds = load_dataset(data)
    except DatasetError as e:
        fail(str(e))
    try:
        tuned = fit_model(method, ds, out, seed=seed, label_fraction=label_fraction, data=str(data))
    except ValueError as e:
        fail(f"{method}: {e}")
    det = tuned.detector
    typer.echo(f"{method}: params {tuned.params}, threshold {det.threshold_:.4g}, "
               f"validation F1 {tuned.val_f1:.3f}; saved {out}")


def evaluate(
    model: Path = typer.Option(..., help=MODEL_HELP),
    data: Path = typer.Option(..., help="Dataset directory to score."),
    out: Path = typer.Option(..., "--out", help="Output directory."),
    test_only: bool = typer.Option(False, help="Score only the test flights of the split the model was fit with."),
    runtime: str = typer.Option("torch", help=RUNTIME_HELP),
    typing: str = typer.Option("shape", help=TYPING_HELP),
) -> None:
    """Score a dataset with a fitted detector; metrics when it has labels."""
    from quadformer.experiments.models import evaluate_model

    check_typing(typing)
    det = load_model_file(model, runtime)
    ds = load_dataset_dir(data)
    try:
        ev = evaluate_model(det, ds, out, model=str(model), data=str(data), test_only=test_only, typing=typing)
    except ValueError as e:
        fail(str(e))
    if ev.metrics is not None:
        m = ev.metrics
        typer.echo(f"{det.name}: P {m['precision']:.3f} R {m['recall']:.3f} F1 {m['f1']:.3f} "
                   f"event F1 {m['event_f1']:.3f}")
    print_alerts(ev.alerts)
    typer.echo(f"wrote {out / 'results.json'}, {out / 'scores.parquet'} and {out / 'alerts.csv'}")


def export(
    model: Path = typer.Option(..., help="Model file written by `quadformer fit` (a network detector)."),
    out: Path = typer.Option(..., "--out", help="The .onnx file to write (NAME.onnx.json is written beside it, and "
                                                "NAME.stream.onnx for QUADFormer)."),
) -> None:
    """Export a network detector (CNN, LSTM, QUADFormer) to ONNX: feature normalisation and score
    inside the graph; features, padding and the alarm rule in a JSON beside it; for QUADFormer
    also its streaming graph (one GPS step and the window's state in)."""
    from quadformer.detectors import load
    from quadformer.detectors.export import export_files, export_onnx

    try:
        det = load(model)
        path = export_onnx(det, out)
    except (FileNotFoundError, ValueError, KeyError) as e:
        fail(message(e))
    names = [p.name for p in export_files(path)]
    typer.echo(f"wrote {path} and {', '.join(names[1:])} ({det.name}, {len(det.features_)} features, window "
               f"{det.window}); score it with --runtime onnx")


def resilience(
    profile: str = typer.Option("demo", help="demo (20 flights/config), quick (60), paper (600) or mixed (60, "
                                "mixed attacks)."),
    detector: str = typer.Option("quadformer", help="Registered detector driving the resilient policy."),
    out: Path = typer.Option(Path("runs/resilience"), "--out", help="Output directory."),
    cache: Path = typer.Option(Path("runs/cache"), help="Dataset and tuned-model cache directory."),
    configs: Optional[str] = typer.Option(None, help=CONFIGS_HELP),
    seed: int = typer.Option(0, help="Split seed (the detection benchmark's)."),
    label_fraction: float = typer.Option(0.2, help="Share of training flights whose labels the detector may use."),
    hold: float = typer.Option(2.0, help="Seconds clear and agreeing before GPS is re-admitted."),
    stale_hold: float = typer.Option(5.0, "--stale-hold", help=STALE_HOLD_HELP),
    blend: float = typer.Option(2.0, help="Seconds over which re-admitted GPS goes from inflated to nominal noise."),
    threshold: str = typer.Option("f1", help="Alarm threshold chosen on validation flights: f1 (max F1) or budget "
                                  "(1 alarm per flight-hour on clean flights)."),
    max_flights: Optional[int] = typer.Option(None, help="Fly only the first N test flights of each configuration "
                                              "(by flight index; default: all)."),
    workers: Optional[int] = typer.Option(None, help="Local worker processes (default: one per core)."),
    backend: str = typer.Option("local", help=BACKEND_HELP),
    address: Optional[str] = typer.Option(None, help=ADDRESS_HELP),
    device: str = typer.Option("auto", help=DEVICE_HELP),
    quiet: bool = typer.Option(False, help="No progress bars."),
) -> None:
    """Fly each configuration's test flights in closed loop under four GPS policies (naive, PX4-like,
    resilient with DETECTOR, oracle); write results.json, alerts.csv, tables and a report."""
    from quadformer.dataset import DatasetError
    from quadformer.experiments.pool import BackendError, UnitError
    from quadformer.experiments.resilience import run_resilience
    from quadformer.io import set_threads
    from quadformer.resilience import AdmissionConfig

    prof = select_profile(profile, configs)
    if not 0.0 <= label_fraction <= 1.0:
        fail(f"label-fraction: must be in [0, 1], got {label_fraction}")
    try:
        adm = AdmissionConfig(hold_s=hold, stale_hold_s=stale_hold, blend_s=blend)
    except ValueError as e:
        fail(str(e))
    if "," in detector:
        fail(f"detector: one name, got {detector!r}")
    if threshold not in ("f1", "budget"):
        fail(f"threshold: unknown choice {threshold!r}; choose from f1, budget")
    if max_flights is not None and max_flights < 1:
        fail(f"max-flights: must be at least 1, got {max_flights}")
    method_names(detector)
    be = check_backend(backend, address, device, workers)
    set_threads()
    try:
        results = run_resilience(prof, detector, out, cache, progress=not quiet, workers=workers, seed=seed,
                                 label_fraction=label_fraction, admission=adm, threshold=threshold,
                                 max_flights=max_flights, backend=be, device=device)
    except (DatasetError, ValueError, BackendError, UnitError) as e:
        fail(str(e))
    print_resilience(results)
    typer.echo(f"\nresilience run took {results['timing_s']['total']:.0f} s")
    typer.echo(f"results: {(out / 'results.json').resolve()}")
    typer.echo(f"alerts:  {(out / 'alerts.csv').resolve()}")
    typer.echo(f"report:  {(out / 'report.html').resolve()}")
