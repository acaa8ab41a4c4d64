"""Command line: builds a config and calls the library. ``quadformer --help``."""

from __future__ import annotations

import sys
import tomllib
from pathlib import Path
from typing import Any, Optional

import typer

from quadformer.config import (ATTACK_CHOICES, ATTACK_KINDS, MIX_KINDS, MODELS, NOISE_SHAPES, SENSOR_CONFIGS,
                               ConfigError, SimConfig, merge)

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="GPS spoofing detection and resilient estimation for quadrotors.")


_RUNTIME_HELP = "torch (the saved model) or onnx (a graph written by `quadformer export`, scored with onnxruntime)."
_TYPING_HELP = ("Where alerts take their attack type from: shape (each attack shape fitted to GPS minus the "
                "GPS-free reference, no labels; where the data has those residues) or detector (its own "
                "classifier; 'attack' from a detector that does not classify).")
_FILTER_HELP = ("The replayed filter's tuning: ekf2 (PX4 EKF2's default noise, the receiver's own accuracy), or "
                "a simulated dataset directory (its filter's tuning, so that the residues have the scale of that "
                "data's).")
_GPS_DELAY_HELP = ("Seconds before its stamp that a fix was measured (the receiver's latency, as the autopilot's "
                   "EKF2_GPS_DELAY or GPS_DELAY_MS); each fix is fused at that time, the filter running that far "
                   "behind the newest IMU sample.")
_LOG_GPS_DELAY_HELP = _GPS_DELAY_HELP + " Default: the autopilot's own setting where the log records it, else 0."
_LIVE_GPS_DELAY_HELP = _GPS_DELAY_HELP + " Default 0 (a link does not carry the autopilot's setting)."
_RECEIVER_HELP = ("Weight each fix by the receiver's stated accuracy (eph, epv, speed accuracy) where it is worse "
                  "than the tuning's GPS noise, as the autopilot does. --no-receiver-accuracy: the tuning's noise "
                  "alone (more sensitive where the receiver overstates its error; a receiver's own meters of error "
                  "then read as a spoof).")
_RESIDUES_HELP = ("ekf: replay the project's filter over the log's sensors; autopilot: the autopilot's own "
                  "logged GPS innovations, whitened by its logged variances.")


def _pair(name: str, text: Optional[str]) -> Optional[list[float]]:
    if text is None:
        return None
    parts = text.replace(":", ",").split(",")
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise typer.BadParameter(f"{name}: expected 'low,high' numbers, got {text!r}") from None
    if len(vals) == 1:
        vals = vals * 2
    if len(vals) != 2:
        raise typer.BadParameter(f"{name}: expected 'low,high', got {text!r}")
    return vals


def _parse_set(items: list[str]) -> dict[str, Any]:
    """--set a.b=value (TOML value syntax; bare words are strings)."""
    out: dict[str, Any] = {}
    for item in items:
        if "=" not in item:
            raise typer.BadParameter(f"--set expects KEY=VALUE, got {item!r}")
        key, raw = item.split("=", 1)
        try:
            value = tomllib.loads(f"v = {raw}")["v"]
        except tomllib.TOMLDecodeError:
            value = raw
        node = out
        parts = key.strip().split(".")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = value
    return out


def _read_config_file(path: Optional[Path]) -> dict[str, Any]:
    if path is None:
        return {}
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise typer.BadParameter(f"--config: no such file {path}") from None
    except tomllib.TOMLDecodeError as e:
        raise typer.BadParameter(f"--config: {path} is not valid TOML ({e})") from None


def build_config(config_file: Optional[Path], options: dict[str, Any], sets: list[str],
                 base: Optional[dict[str, Any]] = None) -> SimConfig:
    """TOML file, then ``base`` (e.g. noise fitted to logs), then named options, then --set."""
    data = merge(_read_config_file(config_file), base or {})
    data = merge(data, {k: v for k, v in options.items() if v is not None and not isinstance(v, dict)})
    for k, v in options.items():
        if isinstance(v, dict):
            v = {kk: vv for kk, vv in v.items() if vv is not None}
            if v:
                data = merge(data, {k: v})
    data = merge(data, _parse_set(sets))
    return SimConfig.from_dict(data)


def _fail(msg: str) -> None:
    typer.secho(f"error: {msg}", fg=typer.colors.RED, err=True)
    raise typer.Exit(2)


_BACKEND_HELP = ("Where work units run: local (processes of this machine) or ray (tasks on a Ray cluster; "
                 "pip install 'quadformer\\[ray]').")
_ADDRESS_HELP = ("With --backend ray: auto (the cluster `ray start` started here) or ray://host:port; default: a "
                 "Ray runtime started on this machine.")
_DEVICE_HELP = "Where network detectors train: auto (a GPU when there is one), cpu or cuda."
_STALE_HOLD_HELP = ("Seconds the GPS fixes must agree with the estimate (NIS inside the gate) to re-admit GPS "
                    "while the detector's alarm still stands (a stale alarm: the detector's memory of an attack that "
                    "has ended, not a new onset). The standing alarm then no longer excludes GPS; a new alarm onset "
                    "or a fix outside the gate does. inf: off (only a clear detector re-admits).")


def _backend(kind: str, address: Optional[str], device: str, workers: Optional[int] = None):
    """The backend, checked before any work: Ray installed (and its cluster reachable) for
    ``ray``, and the training device available where the units run."""
    from quadformer.experiments.cache import check_device
    from quadformer.experiments.pool import Backend, BackendError, ray_module

    try:
        be = Backend(kind, address)
        if be.kind == "ray":
            ray_module()
        check_device(device, be, workers)
    except (ValueError, BackendError) as e:
        _fail(str(e))
    return be


def _profile(name: str, configs: Optional[str] = None):
    """The named profile, over the configurations ``configs`` names when given."""
    from quadformer.experiments.grid import get_profile, select_configs

    try:
        prof = get_profile(name)
        return prof if configs is None else select_configs(prof, configs)
    except ValueError as e:
        _fail(str(e))


_CONFIGS_HELP = ("Comma-separated configurations of the profile to run (e.g. modelII-laplace-bias; default: "
                 "all); their datasets and models are the whole profile's, shared through the cache.")


@app.command()
def simulate(
    out: Path = typer.Option(..., "--out", help="Dataset directory to create."),
    model: Optional[str] = typer.Option(None, help=f"UAV model: {', '.join(MODELS)} (default I)."),
    noise: Optional[str] = typer.Option(None, help=f"Noise shape: {', '.join(NOISE_SHAPES)} (default gaussian)."),
    sensors: Optional[str] = typer.Option(None, help=f"Sensor configuration: {', '.join(SENSOR_CONFIGS)} "
                                          "(default gps+imu+vio; names in any order)."),
    attack: Optional[str] = typer.Option(None, help=f"Attack: {', '.join(ATTACK_CHOICES)} (default none); mix: "
                                         "each attacked flight draws its kind from --mix."),
    mix: Optional[str] = typer.Option(None, "--mix", help=f"Kinds a mixed attack draws from, e.g. 'bias,ramp' "
                                      f"(default all: {','.join(MIX_KINDS)})."),
    flights: Optional[int] = typer.Option(None, help="Number of flights (default 8)."),
    duration: Optional[float] = typer.Option(None, help="Seconds per flight (default 60)."),
    seed: Optional[int] = typer.Option(None, help="Dataset seed (default 0)."),
    batch_size: Optional[int] = typer.Option(None, help="Flights simulated together (speed only)."),
    attack_fraction: Optional[float] = typer.Option(None, help="Share of flights attacked (default 0.5)."),
    onset: Optional[str] = typer.Option(None, help="Attack onset range 'low,high' in s."),
    attack_duration: Optional[str] = typer.Option(None, help="Attack duration range 'low,high' in s."),
    magnitude: Optional[str] = typer.Option(None, help="Offset norm range 'low,high' in m."),
    rate: Optional[str] = typer.Option(None, help="Ramp drift rate range 'low,high' in m/s."),
    axes: Optional[str] = typer.Option(None, help="Fixed attacked axes, e.g. 'x' or 'xy'."),
    config: Optional[Path] = typer.Option(None, "--config", help="TOML file with any SimConfig fields."),
    noise_from: list[Path] = typer.Option([], "--noise-from", help="Clean flight log(s) whose GPS, IMU, "
                                          "barometer and magnetometer noise the simulated sensors take "
                                          "(repeatable; over --config, under the named options and --set)."),
    set_: list[str] = typer.Option([], "--set", help="Override any field: --set gps.gm_std=0 (repeatable)."),
    overwrite: bool = typer.Option(False, help="Replace DIR if it exists."),
    quiet: bool = typer.Option(False, help="No progress bar."),
) -> None:
    """Simulate flights and write DIR/flights.parquet, scenarios.parquet and meta.json."""
    from quadformer.dataset import write_dataset
    from quadformer.io import set_threads
    from quadformer.simulation import simulate as run

    atk = {"kind": attack, "fraction": attack_fraction, "onset": _pair("--onset", onset),
           "duration": _pair("--attack-duration", attack_duration), "magnitude": _pair("--magnitude", magnitude),
           "rate": _pair("--rate", rate), "axes": axes, "mix": mix.split(",") if mix is not None else None}
    fitted = None
    if noise_from:
        from quadformer.logs import LogError, read_log
        from quadformer.logs.noise import estimate_noise

        try:
            fitted = estimate_noise([read_log(p) for p in _log_paths(noise_from, None)])
        except LogError as e:
            _fail(f"noise-from: {e}")
        typer.echo("sensor noise from the logs: " + ", ".join(
            f"{k} {v:.4g}" for k, v in fitted.to_dict().items() if isinstance(v, float)))
    try:
        cfg = build_config(config, {"model": model, "noise": noise, "sensors": sensors, "flights": flights,
                                    "duration": duration, "seed": seed, "batch_size": batch_size, "attack": atk},
                           set_, base=fitted.sim_overrides() if fitted else None)
    except (ConfigError, TypeError) as e:
        _fail(str(e))
    if out.exists() and not overwrite:
        _fail(f"{out} already exists (use --overwrite to replace it)")
    set_threads()
    ds = run(cfg, progress=not quiet)
    write_dataset(ds, out, overwrite=overwrite)
    s = ds.meta["summary"]
    typer.echo(f"wrote {out}: {s['flights']} flights ({s['attacked_flights']} attacked), {s['rows']} GPS steps")


def _methods(text: Optional[str]) -> list[str]:
    from quadformer.detectors import available, defaults, get

    if text is None:
        names = defaults()
    elif text == "all":
        names = available()
    else:
        names = [m.strip() for m in text.split(",") if m.strip()]
    for m in names:
        try:
            get(m)
        except KeyError as e:
            _fail(str(e.args[0]))
    return names


def _print_tables(results: dict) -> None:
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
    _print_typing(results)
    _print_stress(results)


def _print_typing(results: dict) -> None:
    from quadformer.report.detection import typing_table

    df = typing_table(results)
    if df is not None:
        typer.echo("\nAttacks typed right, of the detected attacks on test flights (shape typer: no labels)")
        typer.echo(df.to_string())


def _print_stress(results: dict) -> None:
    from quadformer.report.detection import stress_table

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


def _print_seeds(results: dict) -> None:
    from quadformer.report.detection import seeds_table

    typer.echo(f"\nPoint-wise F1 on test flights over seeds {', '.join(map(str, results['seeds']))}: "
               "mean ± std [min, max]")
    typer.echo(seeds_table(results, "f1").to_string())


def _typing(typing: str) -> None:
    from quadformer.detectors.attack_types import TYPINGS

    if typing not in TYPINGS:
        _fail(f"typing: unknown {typing!r}; choose from {', '.join(TYPINGS)}")


def _seed_list(seeds: Optional[int], seed_list: Optional[str], seed: int) -> Optional[list[int]]:
    """--seeds N (seeds seed .. seed+N-1) or --seed-list a,b,c; None for a single run."""
    if seeds is not None and seed_list is not None:
        _fail("seeds: give --seeds or --seed-list, not both")
    if seeds is not None:
        if seeds < 1:
            _fail(f"seeds: must be at least 1, got {seeds}")
        return list(range(seed, seed + seeds))
    if seed_list is not None:
        try:
            out = [int(x) for x in seed_list.split(",") if x.strip()]
        except ValueError:
            _fail(f"seed-list: expected comma-separated integers, got {seed_list!r}")
        if not out or len(set(out)) != len(out) or min(out) < 0:
            _fail(f"seed-list: expected distinct non-negative integers, got {seed_list!r}")
        return out
    return None


@app.command()
def benchmark(
    profile: str = typer.Option("demo", help="demo (20 flights/config), quick (60), paper (600), or mixed (60 "
                                "flights/config of mixed attacks, Model I/II x exponential/Laplace noise)."),
    methods: Optional[str] = typer.Option(None, help="Comma-separated detector names; default: every registered "
                                          "detector except ablations; 'all': every one."),
    data: list[Path] = typer.Option([], "--data", help="Benchmark on these dataset directories instead of a "
                                    "profile (repeatable): simulated ones or `quadformer logs import` ones."),
    configs: Optional[str] = typer.Option(None, help=_CONFIGS_HELP),
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
    backend: str = typer.Option("local", help=_BACKEND_HELP),
    address: Optional[str] = typer.Option(None, help=_ADDRESS_HELP),
    device: str = typer.Option("auto", help=_DEVICE_HELP),
    quiet: bool = typer.Option(False, help="No progress bars."),
) -> None:
    """Simulate (or reuse) the profile's configurations, tune and evaluate methods, write tables and a
    report. With --data, the same protocol on given datasets."""
    from quadformer.dataset import DatasetError
    from quadformer.experiments.detection import run_benchmark, run_datasets, run_seeds
    from quadformer.experiments.pool import BackendError, UnitError
    from quadformer.io import set_threads

    if data and configs is not None:
        _fail("--configs selects a profile's configurations; with --data the datasets are given")
    prof = None if data else _profile(profile, configs)
    if not 0.0 <= label_fraction <= 1.0:
        _fail(f"label-fraction: must be in [0, 1], got {label_fraction}")
    seed_runs = _seed_list(seeds, seed_list, seed)
    if data and (stress or seed_runs is not None):
        _fail("--stress, --seeds and --seed-list need a profile (simulated datasets), not --data")
    names = _methods(methods)
    be = _backend(backend, address, device, workers)
    if data and be.kind != "local":
        _fail("--data runs in this process; --backend ray needs a profile")
    set_threads()
    try:
        if data:
            results = run_datasets(data, names, out, progress=not quiet, seed=seed, label_fraction=label_fraction,
                                   device=device)
        elif seed_runs is not None:
            results = run_seeds(prof, names, out, cache, seed_runs, progress=not quiet, workers=workers,
                                label_fraction=label_fraction, stress=stress, backend=be, device=device)
        else:
            results = run_benchmark(prof, names, out, cache, progress=not quiet, workers=workers, seed=seed,
                                    label_fraction=label_fraction, stress=stress, backend=be, device=device)
    except (DatasetError, ValueError, BackendError, UnitError) as e:
        _fail(str(e))
    if seed_runs is not None:
        _print_seeds(results)
        typer.echo(f"\nbenchmark over {len(seed_runs)} seeds took {results['timing_s']['total']:.0f} s; each seed's "
                   f"tables and report in {out}/seed-<s>/")
        typer.echo(f"results: {(out / 'results.json').resolve()}")
        typer.echo(f"report:  {(out / 'report.html').resolve()}")
        return
    _print_tables(results)
    typer.echo(f"\nbenchmark took {results['timing_s']['total']:.0f} s "
               f"(simulation {results['timing_s']['simulate']:.0f} s)")
    typer.echo(f"results: {(out / 'results.json').resolve()}")
    typer.echo(f"report:  {(out / 'report.html').resolve()}")


@app.command()
def fit(
    method: str = typer.Option(..., help="Detector name."),
    data: Path = typer.Option(..., help="Dataset directory (from `quadformer simulate`)."),
    out: Path = typer.Option(..., "--out", help="Model file to write (JSON)."),
    seed: int = typer.Option(0, help="Split seed."),
    label_fraction: float = typer.Option(0.2, help="Share of training flights whose labels may be used."),
) -> None:
    """Fit and calibrate one detector on a dataset's train and validation flights."""
    from quadformer.dataset import DatasetError, load_dataset
    from quadformer.evaluation.protocol import split_flights, tune

    _methods(method)
    try:
        ds = load_dataset(data)
    except DatasetError as e:
        _fail(str(e))
    sp = split_flights(ds.scenarios, seed, label_fraction=label_fraction)
    parts = sp.frames(ds.flights)
    try:
        tuned = tune(method, parts.train, parts.y_train, parts.val, gps_rate_hz=ds.gps_rate_hz)
    except ValueError as e:
        _fail(f"{method}: {e}")
    det = tuned.detector
    det.calibrate(det.threshold_, det.budget_threshold_, data=str(data), split_seed=seed,
                  label_fraction=label_fraction, test_flights=sp.test.tolist(),
                  sim_config=ds.meta.get("config"))      # the filter tuning its residues came from
    det.save(out)
    typer.echo(f"{method}: params {tuned.params}, threshold {det.threshold_:.4g}, "
               f"validation F1 {tuned.val_f1:.3f}; saved {out}")


@app.command()
def evaluate(
    model: Path = typer.Option(..., help="Model file written by `quadformer fit` (or `quadformer export`'s .onnx "
                               "with --runtime onnx)."),
    data: Path = typer.Option(..., help="Dataset directory to score."),
    out: Path = typer.Option(..., "--out", help="Output directory."),
    test_only: bool = typer.Option(False, help="Score only the test flights of the split the model was fit with."),
    runtime: str = typer.Option("torch", help=_RUNTIME_HELP),
    typing: str = typer.Option("shape", help=_TYPING_HELP),
) -> None:
    """Score a dataset with a fitted detector; metrics when it has labels."""
    import numpy as np

    from quadformer.dataset import DatasetError, load_dataset
    from quadformer.detectors import alerts_from_scores, write_alerts
    from quadformer.detectors.attack_types import alert_typer
    from quadformer.evaluation.metrics import evaluate as metrics
    from quadformer.io import atomic_path, write_json

    _typing(typing)
    det = _load_model(model, runtime)
    try:
        ds = load_dataset(data)
    except (DatasetError, FileNotFoundError, ValueError, KeyError) as e:
        _fail(str(e.args[0] if e.args else e))
    f = ds.flights
    if test_only:
        f = f[f.flight_id.isin(getattr(det, "calibration_", {}).get("test_flights", []))].reset_index(drop=True)
    try:
        s = det.decision_function(f)
    except ValueError as e:
        _fail(str(e))
    alarms = (s > det.threshold_).astype(np.int8)
    out.mkdir(parents=True, exist_ok=True)
    table = f[["flight_id", "t"]].copy()
    table["score"] = s
    table["alarm"] = alarms
    res = {"model": str(model), "data": str(data), "method": det.name, "threshold": det.threshold_,
           "flights": int(f.flight_id.nunique()), "steps": int(len(f))}
    if "label" in f.columns:
        table["label"] = f["label"].to_numpy()
        offsets = np.linalg.norm(f[["atk_d_x", "atk_d_y", "atk_d_z"]].to_numpy(), axis=1) \
            if "atk_d_x" in f.columns else None
        res["metrics"] = metrics(f.flight_id.to_numpy(), f.t.to_numpy(), f.label.to_numpy(), s, alarms == 1,
                                 gps_rate_hz=ds.gps_rate_hz, offsets=offsets)
    with atomic_path(out / "scores.parquet") as tmp:
        table.to_parquet(tmp, index=False)
    alerts = alerts_from_scores(f, s, det, typer=alert_typer(f, typing))
    write_alerts(alerts, out / "alerts.csv")
    res["alerts"] = len(alerts)
    write_json(out / "results.json", res)
    if "metrics" in res:
        m = res["metrics"]
        typer.echo(f"{det.name}: P {m['precision']:.3f} R {m['recall']:.3f} F1 {m['f1']:.3f} "
                   f"event F1 {m['event_f1']:.3f}")
    _print_alerts(alerts)
    typer.echo(f"wrote {out / 'results.json'}, {out / 'scores.parquet'} and {out / 'alerts.csv'}")


def _load_model(path: Path, runtime: str):
    from quadformer.detectors.export import load_model

    try:
        return load_model(path, runtime)
    except (FileNotFoundError, ValueError, KeyError) as e:
        _fail(str(e.args[0] if e.args else e))


@app.command()
def export(
    model: Path = typer.Option(..., help="Model file written by `quadformer fit` (a network detector)."),
    out: Path = typer.Option(..., "--out", help="The .onnx file to write (NAME.onnx.json is written beside it)."),
) -> None:
    """Export a network detector (CNN, LSTM, QUADFormer) to ONNX: feature normalisation and score
    inside the graph; features, padding and the alarm rule in a JSON beside it."""
    from quadformer.detectors import load
    from quadformer.detectors.export import export_onnx

    try:
        det = load(model)
        path = export_onnx(det, out)
    except (FileNotFoundError, ValueError, KeyError) as e:
        _fail(str(e.args[0] if e.args else e))
    typer.echo(f"wrote {path} and {path.name}.json ({det.name}, {len(det.features_)} features, window "
               f"{det.window}); score it with --runtime onnx")


def _print_alerts(alerts, limit: int = 10) -> None:
    typer.echo(f"{len(alerts)} alert(s)" + (":" if alerts else ""))
    for a in alerts[:limit]:
        typer.echo(f"  {a}")
    if len(alerts) > limit:
        typer.echo(f"  ... {len(alerts) - limit} more")


def _print_resilience(results: dict) -> None:
    from quadformer.report import overall_table

    typer.echo(f"\nResilience, detector {results['detector']}, all configurations (test flights flown again "
               "under each policy):")
    typer.echo(overall_table(results).to_string(index=False, na_rep="-", float_format=lambda v: f"{v:.2f}"))
    typer.echo("exclusion P / R / F1: every GPS step a prediction, GPS excluded, against GPS spoofed (point-wise)")
    n = sum(c.get("alerts", 0) for c in results["configs"])
    typer.echo(f"{n} alert(s) raised on the resilient flights (start, estimated onset, type, peak score, end, "
               "type confirmed 5 s later) in alerts.csv")


@app.command()
def resilience(
    profile: str = typer.Option("demo", help="demo (20 flights/config), quick (60), paper (600) or mixed (60, "
                                "mixed attacks)."),
    detector: str = typer.Option("quadformer", help="Registered detector driving the resilient policy."),
    out: Path = typer.Option(Path("runs/resilience"), "--out", help="Output directory."),
    cache: Path = typer.Option(Path("runs/cache"), help="Dataset and tuned-model cache directory."),
    configs: Optional[str] = typer.Option(None, help=_CONFIGS_HELP),
    seed: int = typer.Option(0, help="Split seed (the detection benchmark's)."),
    label_fraction: float = typer.Option(0.2, help="Share of training flights whose labels the detector may use."),
    hold: float = typer.Option(2.0, help="Seconds clear and agreeing before GPS is re-admitted."),
    stale_hold: float = typer.Option(5.0, "--stale-hold", help=_STALE_HOLD_HELP),
    blend: float = typer.Option(2.0, help="Seconds over which re-admitted GPS goes from inflated to nominal noise."),
    threshold: str = typer.Option("f1", help="Alarm threshold chosen on validation flights: f1 (max F1) or budget "
                                  "(1 alarm per flight-hour on clean flights)."),
    max_flights: Optional[int] = typer.Option(None, help="Fly only the first N test flights of each configuration "
                                              "(by flight index; default: all)."),
    workers: Optional[int] = typer.Option(None, help="Local worker processes (default: one per core)."),
    backend: str = typer.Option("local", help=_BACKEND_HELP),
    address: Optional[str] = typer.Option(None, help=_ADDRESS_HELP),
    device: str = typer.Option("auto", help=_DEVICE_HELP),
    quiet: bool = typer.Option(False, help="No progress bars."),
) -> None:
    """Fly each configuration's test flights in closed loop under four GPS policies (naive, PX4-like,
    resilient with DETECTOR, oracle); write results.json, alerts.csv, tables and a report."""
    from quadformer.dataset import DatasetError
    from quadformer.experiments.pool import BackendError, UnitError
    from quadformer.experiments.resilience import run_resilience
    from quadformer.io import set_threads
    from quadformer.resilience import AdmissionConfig

    prof = _profile(profile, configs)
    if not 0.0 <= label_fraction <= 1.0:
        _fail(f"label-fraction: must be in [0, 1], got {label_fraction}")
    try:
        adm = AdmissionConfig(hold_s=hold, stale_hold_s=stale_hold, blend_s=blend)
    except ValueError as e:
        _fail(str(e))
    if "," in detector:
        _fail(f"detector: one name, got {detector!r}")
    if threshold not in ("f1", "budget"):
        _fail(f"threshold: unknown choice {threshold!r}; choose from f1, budget")
    if max_flights is not None and max_flights < 1:
        _fail(f"max-flights: must be at least 1, got {max_flights}")
    _methods(detector)
    be = _backend(backend, address, device, workers)
    set_threads()
    try:
        results = run_resilience(prof, detector, out, cache, progress=not quiet, workers=workers, seed=seed,
                                 label_fraction=label_fraction, admission=adm, threshold=threshold,
                                 max_flights=max_flights, backend=be, device=device)
    except (DatasetError, ValueError, BackendError, UnitError) as e:
        _fail(str(e))
    _print_resilience(results)
    typer.echo(f"\nresilience run took {results['timing_s']['total']:.0f} s")
    typer.echo(f"results: {(out / 'results.json').resolve()}")
    typer.echo(f"alerts:  {(out / 'alerts.csv').resolve()}")
    typer.echo(f"report:  {(out / 'report.html').resolve()}")


def _replay_config(sensors: Optional[str], imu_rate: Optional[float], gps_rate: Optional[float],
                   min_segment: float, filter: str, det=None, gps_delay: Optional[float] = None,
                   receiver_accuracy: bool = True):
    """The replay's filter tuning: EKF2's defaults, the simulation a model was fit on, or a
    simulated dataset's; explicit rates override it."""
    from quadformer.dataset import DatasetError, load_dataset
    from quadformer.estimator.online import FilterConfig

    over = {k: v for k, v in (("sensors", sensors), ("imu_rate_hz", imu_rate), ("gps_rate_hz", gps_rate),
                              ("min_segment_s", min_segment), ("gps_delay_s", gps_delay),
                              ("receiver_accuracy", receiver_accuracy)) if v is not None}
    try:
        if filter == "ekf2":
            return FilterConfig(**over)
        if filter == "model":
            sim = getattr(det, "calibration_", {}).get("sim_config") if det is not None else None
            if sim is None:
                typer.echo("filter: the model does not name the simulation it was fit on; using EKF2's defaults")
                return FilterConfig(**over)
            return FilterConfig.matching(sim, **over)
        try:
            ds = load_dataset(filter)
        except DatasetError as e:
            _fail(f"filter: expected ekf2, model or a simulated dataset directory: {e}")
        if "config" not in ds.meta:
            _fail(f"filter: {filter} is not a simulated dataset")
        return FilterConfig.matching(ds.meta["config"], **over)
    except ValueError as e:
        _fail(str(e))


def _log_paths(paths: list[Path], format: Optional[str]) -> list[Path]:
    """The logs named, directories searched for files whose content is a known log format."""
    from quadformer.logs import FORMATS, detect_format

    if format is not None and format not in FORMATS:
        _fail(f"format: unknown format {format!r}; choose from {', '.join(FORMATS)}")
    out: list[Path] = []
    for p in paths:
        if not p.exists():
            _fail(f"{p}: no such file or directory")
        if p.is_dir() and detect_format(p) is None:
            found = sorted(q for q in p.rglob("*") if (q.is_file() or q.is_dir()) and detect_format(q) is not None
                           and not any(detect_format(par) for par in q.parents if par != p and p in par.parents))
            if not found:
                _fail(f"{p}: no flight log in this directory (PX4 .ulg, ArduPilot .bin, ROS bags)")
            out += found
        else:
            out.append(p)
    return out


@app.command()
def detect(
    logs: list[Path] = typer.Argument(..., help="Flight logs (PX4 .ulg, ArduPilot .bin, ROS 1/2 bags) or "
                                      "directories holding them."),
    model: Path = typer.Option(..., help="Model file written by `quadformer fit` (or `quadformer export`'s .onnx "
                               "with --runtime onnx)."),
    runtime: str = typer.Option("torch", help=_RUNTIME_HELP),
    residues: str = typer.Option("ekf", help=_RESIDUES_HELP),
    out: Path = typer.Option(Path("runs/detect"), "--out", help="Output directory (one folder per log)."),
    format: Optional[str] = typer.Option(None, help="Force a reader: px4, ardupilot or ros (default: detected)."),
    sensors: Optional[str] = typer.Option(None, help="Sensors the replayed filter fuses, e.g. gps+imu+mag+baro "
                                          "(default: every sensor the log has)."),
    filter: str = typer.Option("model", help=_FILTER_HELP + " model: the simulation the detector was fit on "
                               "(EKF2's defaults when the model does not say)."),
    imu_rate: Optional[float] = typer.Option(None, help="IMU averaged down to at most this rate (Hz; default "
                                             "100, or the matched simulation's)."),
    gps_rate: Optional[float] = typer.Option(None, help="At most this many fixes per second are fused (Hz; "
                                             "default 10, or the matched simulation's)."),
    min_segment: float = typer.Option(3.0, help="Seconds of GPS a segment needs to be replayed."),
    gps_delay: Optional[float] = typer.Option(None, help=_LOG_GPS_DELAY_HELP),
    receiver_accuracy: bool = typer.Option(True, help=_RECEIVER_HELP),
    typing: str = typer.Option("shape", help=_TYPING_HELP),
    quiet: bool = typer.Option(False, help="No progress bar."),
) -> None:
    """Detect GPS spoofing in flight logs: per-step scores, alerts (printed and CSV) and a report per log."""
    import numpy as np
    import pandas as pd

    from quadformer.detectors import alerts_frame
    from quadformer.io import atomic_dir, atomic_path, set_threads, write_json
    from quadformer.logs import LogError
    from quadformer.logs.detect import DetectorInputError, NothingToScore, detect_log
    from quadformer.report.logs import write_log_report, write_unscored_report

    det = _load_model(model, runtime)
    if getattr(det, "threshold_", None) is None:
        _fail(f"{model}: the detector has no alarm threshold; write it with `quadformer fit`")
    if residues not in ("ekf", "autopilot"):
        _fail(f"residues: unknown source {residues!r}; choose from ekf, autopilot")
    _typing(typing)
    config = _replay_config(sensors, imu_rate, gps_rate, min_segment, filter, det, gps_delay, receiver_accuracy)
    paths = _log_paths(logs, format)
    set_threads(1)
    bar = None
    if not quiet and len(paths) > 1:
        from tqdm.auto import tqdm
        bar = tqdm(total=len(paths), unit="log", desc="detect")
    summary, all_alerts, failed, skipped = [], [], [], []
    used: set[str] = set()
    for path in paths:
        name = path.name
        while name in used:
            name = f"{path.parent.name}-{name}" if not name.startswith(path.parent.name) else f"{name}-1"
        used.add(name)
        try:
            res = detect_log(path, det, residues, config, format=format, typing=typing)
        except NothingToScore as e:                      # readable, but no GPS or too short: say so
            with atomic_dir(out / name, overwrite=True) as tmp:
                write_unscored_report(e.log, str(e), tmp)
                write_json(tmp / "summary.json", {"log": str(path), "format": e.log.source, "scored": False,
                                                  "reason": str(e), "notes": e.log.notes})
            skipped.append(path)
            typer.echo(f"{path}: nothing scored: {e}")
            if bar is not None:
                bar.update(1)
            continue
        except (LogError, DetectorInputError, ValueError) as e:
            failed.append((path, str(e)))
            typer.secho(f"{path}: {e}", fg=typer.colors.RED, err=True)
            if bar is not None:
                bar.update(1)
            continue
        frame = alerts_frame(res.alerts)
        with atomic_dir(out / name, overwrite=True) as tmp:
            table = res.rows.copy()
            table["score"] = res.scores
            table["alarm"] = res.alarms.astype(np.int8)
            table.to_csv(tmp / "scores.csv", index=False)
            frame.to_csv(tmp / "alerts.csv", index=False)
            write_log_report(res, tmp, str(model))
            info = {"log": str(path), "format": res.log.source, "residues": residues, "sensors": res.sensors,
                    "detector": det.name, "model": str(model), "threshold": det.threshold_,
                    "duration_s": res.log.duration, "segments": len(res.log.segments),
                    "steps": int(len(res.rows)), "alarmed_steps": int(res.alarms.sum()), "alerts": len(res.alerts),
                    "notes": [*res.log.notes, *res.notes]}
            write_json(tmp / "summary.json", info)
        summary.append({k: info[k] for k in ("log", "format", "duration_s", "segments", "steps", "alarmed_steps",
                                             "alerts")})
        all_alerts.append(frame.assign(log=str(path)))
        if bar is not None:
            bar.update(1)
        hours = len(res.rows) / config.gps_rate_hz / 3600
        typer.echo(f"{path}: {res.log.source}, {res.log.duration:.1f} s, {len(res.rows)} GPS steps scored "
                   f"({residues} residues, {res.sensors}): {len(res.alerts)} alert(s) "
                   f"({len(res.alerts) / hours:.1f} per flight-hour)" if hours else "")
        _print_alerts(res.alerts)
    if bar is not None:
        bar.close()
    if summary:
        with atomic_path(out / "summary.csv") as tmp:
            pd.DataFrame(summary).to_csv(tmp, index=False)
        with atomic_path(out / "alerts.csv") as tmp:
            pd.concat(all_alerts, ignore_index=True).to_csv(tmp, index=False)
        typer.echo(f"wrote {out.resolve()}: a folder per log (report.html, scores.csv, alerts.csv, summary.json), "
                   "summary.csv and alerts.csv")
    if skipped:
        typer.echo(f"{len(skipped)} of {len(paths)} log(s) had nothing to score (their report says why)")
    if failed:
        typer.secho(f"{len(failed)} of {len(paths)} log(s) could not be processed", fg=typer.colors.RED, err=True)
        raise typer.Exit(2 if len(failed) == len(paths) else 1)


# -- live monitor ------------------------------------------------------------------------------
_ACT_HELP = ("Act on the vehicle (ArduPilot): on GPS exclusion send MAV_CMD_SET_EKF_SOURCE_SET with the source set "
             "of --act-source-set, and set 1 on re-admission. Off by default. Risks: the vehicle must have a "
             "non-GPS position source configured in that set (EK3_SRC2_*: optical flow, external navigation); "
             "otherwise its EKF loses position. A false alarm switches a flying vehicle's navigation source; "
             "GPS stays excluded after the monitor stops.")


@app.command()
def monitor(
    connect: Optional[str] = typer.Option(None, help="pymavlink connection: udpin:127.0.0.1:14550 (listen, e.g. "
                                          "for MAVProxy --out or mavlink-router), udpout:HOST:PORT, tcp:HOST:PORT, "
                                          "or a serial device /dev/ttyACM0,921600."),
    model: Optional[Path] = typer.Option(None, help="Model file written by `quadformer fit` (or `quadformer "
                                         "export`'s .onnx with --runtime onnx)."),
    runtime: str = typer.Option("torch", help=_RUNTIME_HELP),
    sensors: Optional[str] = typer.Option(None, help="Sensors the monitor's filter fuses, e.g. gps+imu+mag "
                                          "(default: those the detector was fit with)."),
    filter: str = typer.Option("model", help=_FILTER_HELP + " model: the simulation the detector was fit on "
                               "(EKF2's defaults when the model does not say)."),
    imu_rate: Optional[float] = typer.Option(None, help="IMU averaged down to at most this rate (Hz)."),
    gps_rate: Optional[float] = typer.Option(None, help="At most this many fixes per second are fused (Hz)."),
    gps_delay: Optional[float] = typer.Option(None, help=_LIVE_GPS_DELAY_HELP),
    receiver_accuracy: bool = typer.Option(True, help=_RECEIVER_HELP),
    gps_instance: Optional[int] = typer.Option(None, help="GPS receiver: 0 (GPS_RAW_INT) or 1 (GPS2_RAW); "
                                               "default: the first with a 3D fix."),
    system: Optional[int] = typer.Option(None, help="Vehicle system id (default: the first sending sensor data)."),
    out: Optional[Path] = typer.Option(None, "--out", help="Directory for alerts.jsonl, fixes.csv and "
                                       "summary.json (default: console only)."),
    act: bool = typer.Option(False, "--act", help=_ACT_HELP),
    act_source_set: int = typer.Option(2, help="The vehicle's EKF source set without GPS (1..3), for --act."),
    hold: float = typer.Option(2.0, help="Seconds clear and agreeing before GPS is re-admitted."),
    stale_hold: float = typer.Option(5.0, "--stale-hold", help=_STALE_HOLD_HELP),
    blend: float = typer.Option(2.0, help="Seconds of inflated GPS noise after re-admission (reported)."),
    statustext: bool = typer.Option(True, help="Send STATUSTEXT alerts to the vehicle."),
    request_rates: bool = typer.Option(False, help="Ask the vehicle for the streams the monitor needs "
                                       "(SET_MESSAGE_INTERVAL)."),
    duration: Optional[float] = typer.Option(None, help="Stop after this many seconds (default: Ctrl-C)."),
    max_messages: Optional[int] = typer.Option(None, help="Stop after this many messages."),
    demo: bool = typer.Option(False, "--demo", help="Fit a quick detector on simulated flights (unless --model), "
                              "stream a simulated spoofed flight from 127.0.0.1 to the monitor and show the alert."),
    speed: float = typer.Option(5.0, help="--demo: the flight is streamed at this many times real time."),
    typing: str = typer.Option("shape", help=_TYPING_HELP + " With shape, each alert's type is confirmed "
                               "5 s after it was raised (console, alerts.jsonl)."),
) -> None:
    """Watch a live vehicle's GPS over MAVLink: the filter and detector of `detect`, one message at a
    time; alerts on the console, as STATUSTEXT to the vehicle and in --out; with --act, switch the
    vehicle's EKF source set when GPS is excluded."""
    from quadformer.io import set_threads
    from quadformer.live.monitor import Monitor, MonitorConfig
    from quadformer.resilience import AdmissionConfig

    set_threads(1)
    try:
        adm = AdmissionConfig(hold_s=hold, stale_hold_s=stale_hold, blend_s=blend)
    except ValueError as e:
        _fail(str(e))
    det = _load_model(model, runtime) if model is not None else None
    if det is not None and getattr(det, "threshold_", None) is None:
        _fail(f"{model}: the detector has no alarm threshold; write it with `quadformer fit`")
    if demo:
        from quadformer.experiments.live_demo import run_demo

        run_demo(out, detector=det, speed=speed, duration_s=duration, act=act, echo=typer.echo,
                 model_path=str(model) if model else None)
        return
    if det is None:
        _fail("--model is required (or --demo)")
    if connect is None:
        _fail("--connect is required, e.g. --connect udpin:127.0.0.1:14550")
    filt = _replay_config(sensors, imu_rate, gps_rate, 3.0, filter, det, gps_delay, receiver_accuracy)
    try:
        config = MonitorConfig(connect=connect, filter=filt, admission=adm, gps_instance=gps_instance, system=system,
                               act=act, act_source_set=act_source_set, statustext=statustext,
                               request_rates=request_rates, out=out, duration_s=duration, max_messages=max_messages,
                               typing=typing)
        mon = Monitor(det, config, echo=typer.echo, model=str(model))
        mon.open()
    except (ValueError, OSError) as e:
        _fail(str(e))
    if act:
        typer.secho(f"--act: GPS exclusion will switch the vehicle to EKF source set {act_source_set}",
                    fg=typer.colors.YELLOW)
    mon.run()
    if out is not None:
        typer.echo(f"wrote {out.resolve()}: alerts.jsonl, fixes.csv, summary.json")


logs_app = typer.Typer(no_args_is_help=True, help="Flight logs: what a log holds; datasets from logs.")
app.add_typer(logs_app, name="logs")


@logs_app.command("info")
def logs_info(
    log: Path = typer.Argument(..., help="A flight log."),
    format: Optional[str] = typer.Option(None, help="Force a reader: px4, ardupilot or ros."),
) -> None:
    """What a log holds: streams with their rates, segments, origin and the reader's notes."""
    import numpy as np

    from quadformer.logs import LogError, read_log

    try:
        fl = read_log(log, format=format)
    except LogError as e:
        _fail(str(e))
    typer.echo(f"{log}: {fl.source}, {fl.duration:.1f} s in {len(fl.segments)} segment(s), origin {fl.origin} "
               f"({fl.origin_source})")
    for k, v in fl.vehicle.items():
        typer.echo(f"  {k}: {v}")
    for name, df in fl.streams.items():
        t = df["t"].to_numpy()
        rate = 1.0 / np.median(np.diff(t)) if len(t) > 1 else float("nan")
        typer.echo(f"  {name:12s} {len(df):7d} samples, {rate:7.1f} Hz, {t[0]:.2f} to {t[-1]:.2f} s")
    for n in fl.notes:
        typer.echo(f"  note: {n}")


@logs_app.command("import")
def logs_import(
    logs: list[Path] = typer.Argument(..., help="Flight logs or directories holding them."),
    out: Path = typer.Option(..., "--out", help="Dataset directory to create."),
    residues: str = typer.Option("ekf", help=_RESIDUES_HELP),
    inject: Optional[str] = typer.Option(None, help=f"Spoof to inject into the logged GPS before the replay: "
                                         f"{', '.join(k for k in ATTACK_KINDS if k != 'none')} (open loop)."),
    attack_fraction: Optional[float] = typer.Option(None, help="Share of flights attacked (default 0.5)."),
    onset: Optional[str] = typer.Option(None, help="Attack onset range 'low,high' in s from each flight's first "
                                        "fix (clipped to the flight's first half)."),
    attack_duration: Optional[str] = typer.Option(None, help="Attack duration range 'low,high' in s."),
    magnitude: Optional[str] = typer.Option(None, help="Offset norm range 'low,high' in m."),
    rate: Optional[str] = typer.Option(None, help="Ramp drift rate range 'low,high' in m/s."),
    axes: Optional[str] = typer.Option(None, help="Fixed attacked axes, e.g. 'x' or 'xy'."),
    seed: int = typer.Option(0, help="Seed of which flights are attacked and of the attacks' parameters."),
    repeat: int = typer.Option(1, help="Replay each log segment this many times (each with its own injection)."),
    group: bool = typer.Option(True, help="Keep the replays of one recording together in the benchmark's split "
                               "(--no-group: split them like independent flights; optimistic, for a fleet of "
                               "too few logs to split by recording)."),
    format: Optional[str] = typer.Option(None, help="Force a reader: px4, ardupilot or ros."),
    sensors: Optional[str] = typer.Option(None, help="Sensors the replayed filter fuses (default: all the log has)."),
    filter: str = typer.Option("ekf2", help=_FILTER_HELP),
    imu_rate: Optional[float] = typer.Option(None, help="IMU averaged down to at most this rate (Hz; default 100)."),
    gps_rate: Optional[float] = typer.Option(None, help="At most this many fixes per second are fused (Hz; "
                                             "default 10)."),
    min_segment: float = typer.Option(3.0, help="Seconds of GPS a segment needs to be replayed."),
    gps_delay: Optional[float] = typer.Option(None, help=_LOG_GPS_DELAY_HELP),
    receiver_accuracy: bool = typer.Option(True, help=_RECEIVER_HELP),
    overwrite: bool = typer.Option(False, help="Replace DIR if it exists."),
) -> None:
    """A dataset (the format of `quadformer simulate`) from flight logs: one flight per log segment,
    optionally with spoofs injected into the logged GPS and labelled. `benchmark --data`, `fit` and
    `evaluate` take it."""
    from quadformer.config import AttackConfig
    from quadformer.dataset import write_dataset
    from quadformer.io import set_threads
    from quadformer.logs import LogError
    from quadformer.logs.detect import logs_dataset

    if residues not in ("ekf", "autopilot"):
        _fail(f"residues: unknown source {residues!r}; choose from ekf, autopilot")
    if out.exists() and not overwrite:
        _fail(f"{out} already exists (use --overwrite to replace it)")
    attack = None
    if inject is not None:
        opts = {"kind": inject, "fraction": attack_fraction, "onset": _pair("--onset", onset),
                "duration": _pair("--attack-duration", attack_duration), "magnitude": _pair("--magnitude", magnitude),
                "rate": _pair("--rate", rate), "axes": axes}
        try:
            attack = AttackConfig(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in opts.items()
                                     if v is not None})
        except (ConfigError, TypeError) as e:
            _fail(str(e))
    config = _replay_config(sensors, imu_rate, gps_rate, min_segment, filter, gps_delay=gps_delay,
                            receiver_accuracy=receiver_accuracy)
    paths = _log_paths(logs, format)
    set_threads(1)
    try:
        ds = logs_dataset(paths, residues, config, attack=attack, seed=seed, format=format, repeat=repeat,
                          group=group)
    except (LogError, ValueError) as e:
        _fail(str(e))
    write_dataset(ds, out, overwrite=overwrite)
    s = ds.meta["summary"]
    for log, notes in ds.meta["notes"].items():
        for n in notes:
            typer.echo(f"{log}: {n}")
    typer.echo(f"wrote {out}: {s['flights']} flights ({s['attacked_flights']} attacked) from {len(paths)} log(s), "
               f"{s['rows']} GPS steps, {residues} residues")


@app.command()
def demo(
    out: Path = typer.Option(Path("runs/demo"), "--out", help="Output directory."),
    cache: Path = typer.Option(Path("runs/cache"), help="Dataset and tuned-model cache directory."),
    quiet: bool = typer.Option(False, help="No progress bars."),
) -> None:
    """The demo profile end to end: simulate, residues, every detector, tables, report; then a
    short resilience run over four of the configurations (QUADFormer driving the resilient
    estimator, beside the other policies)."""
    from quadformer.dataset import load_dataset
    from quadformer.experiments.cache import ensure_datasets
    from quadformer.experiments.demo import plan
    from quadformer.experiments.detection import run_benchmark
    from quadformer.experiments.grid import PROFILES, dataset_summary, summary_table
    from quadformer.experiments.pool import SharedBar
    from quadformer.experiments.resilience import run_resilience
    from quadformer.io import set_threads

    import time

    t0 = time.perf_counter()
    set_threads()
    profile = PROFILES["demo"]
    methods = _methods(None)
    todo = plan(profile, methods, cache, resilience=True)
    typer.echo(todo.describe())
    bar = None if quiet else SharedBar(todo.units, desc="demo")
    progress = bar if bar is not None else False
    phases = {}
    try:
        paths = ensure_datasets(profile, cache, progress=progress)
        phases["simulate"] = time.perf_counter() - t0
        rows = [{"config": name, **dataset_summary(load_dataset(p))} for name, p in paths.items()]
        t1 = time.perf_counter()
        results = run_benchmark("demo", methods, out / "detection", cache, progress=progress)
        phases["detection"] = time.perf_counter() - t1
        t1 = time.perf_counter()
        res = run_resilience("demo", "quadformer", out / "resilience", cache, progress=progress)
        phases["resilience"] = time.perf_counter() - t1
    finally:
        if bar is not None:
            bar.close()
    typer.echo("Datasets (GPS noise moments: velocity error on clean steps, std set to 0.1 m/s):")
    typer.echo(summary_table(rows).to_string(index=False))
    _print_tables(results)
    _print_resilience(res)
    typer.echo(f"\ndemo took {time.perf_counter() - t0:.0f} s (estimated {todo.estimate_s:.0f} s): "
               + ", ".join(f"{k} {v:.0f} s" for k, v in phases.items()))
    typer.echo(f"detection results: {(out / 'detection' / 'results.json').resolve()}")
    typer.echo(f"detection report:  {(out / 'detection' / 'report.html').resolve()}  (open in a browser; works offline)")
    typer.echo(f"resilience report: {(out / 'resilience' / 'report.html').resolve()}")
    typer.echo(f"alerts:            {(out / 'resilience' / 'alerts.csv').resolve()}")


def main() -> None:  # pragma: no cover
    app()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(app())
