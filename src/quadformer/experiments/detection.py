"""The detection benchmark: a profile's configurations, every method, one protocol.

For each configuration and method the protocol of ``evaluation.protocol`` picks
hyper-parameters and threshold on validation flights; the test flights are scored once.
Datasets and tuned detectors come from the caches of ``experiments.cache``.

Beside the main run: ``stress=True`` scores the tuned detectors on stress datasets outside
their tuning ranges (``experiments.stress``); ``run_shipped`` scores the shipped detectors on a
profile's flights, tuning nothing. ``experiments.seeds`` repeats the whole protocol over several
seeds (datasets and splits) and summarises the spread.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from quadformer.dataset import Dataset, load_dataset
from quadformer.detectors import alerts_frame, alerts_from_scores, flight_slices, get, runs
from quadformer.detectors.alarms import run_starts
from quadformer.detectors.attack_types import TYPING_COLUMNS, ShapeTyper
from quadformer.evaluation.metrics import bootstrap_f1, evaluate, event_recall_by_type
from quadformer.evaluation.protocol import TrainingBudget, split_flights
from quadformer.experiments.cache import (batch_count, check_device, ensure_configs, ensure_tuned, model_dir_for,
                                          tuned_model)
from quadformer.experiments.grid import Profile, get_profile, profile_configs
from quadformer.experiments.zoo import ZOO_SEED, shipped_tuned
from quadformer.experiments.pool import Backend, SharedBar, run_jobs
from quadformer.experiments.provenance import provenance
from quadformer.io import atomic_path, package_versions, write_json

#: bootstrap resamples of the test flights for the F1 interval of a run
N_BOOTSTRAP = 2000


def run_config(ds: Dataset, methods: list[str], seed: int = 0, label_fraction: float = 0.2,
               budget_per_hour: float = 1.0, model_dir: Path | None = None,
               detectors: dict[str, Any] | None = None, device: str | None = None,
               tuning: dict[str, dict[str, Any]] | None = None,
               budget: TrainingBudget | None = None,
               shipped: dict[str, str] | None = None) -> tuple[dict[str, Any], pd.DataFrame]:
    """Tune and evaluate every method on one dataset. Returns (results, per-step test scores).

    shipped: method -> a shipped detector's name (``detectors.pretrained``): nothing is tuned,
    every flight of ``ds`` is a test flight (flights the shipped detectors never saw), each
    method scored at its shipped validation-F1 threshold (and its budget one).

    model_dir: cache of tuned detectors (see ``tuned_model``); None: always tune.
    detectors: if given, receives each method's tuned (calibrated) detector.
    device: where network detectors train when tuned here (resolved; None: the CPU).
    tuning: per method, what ``cache.ensure_tuned`` reported when the models were tuned in
    work units before (``cached``, ``seconds``): recorded as ``model_from_cache`` and
    ``tune_seconds`` instead of the time taken to load them.
    budget: a reduced training budget (None: the full one)."""
    rate = ds.gps_rate_hz
    if shipped is None:
        sp = split_flights(ds.scenarios, seed, label_fraction=label_fraction)
        parts = sp.frames(ds.flights)
        test = parts.test
        split = {"train": len(sp.train), "val": len(sp.val), "test": len(sp.test), "labelled": len(sp.labelled)}
    else:       # nothing to tune: every flight is a test flight
        test = ds.flights
        split = {"train": 0, "val": 0, "test": int(ds.scenarios.shape[0]), "labelled": 0}
    offsets = np.linalg.norm(test[["atk_d_x", "atk_d_y", "atk_d_z"]].to_numpy(), axis=1)
    true_types = np.where(test.label.to_numpy() == 1, test.attack_type.astype(str).to_numpy(), "none")
    scores = test[["flight_id", "t", "label"]].copy()
    out: dict[str, Any] = {}
    alerts: list[pd.DataFrame] = []
    # the shape typer, where the test flights carry its columns; its type of a test row is
    # shared by the methods
    typer = ShapeTyper() if all(c in test.columns for c in TYPING_COLUMNS) else None
    typed: dict[int, str] = {}
    for m in methods:
        t0 = time.perf_counter()
        tuned = (shipped_tuned(shipped[m]) if shipped is not None else
                 tuned_model(m, parts.train, parts.y_train, parts.val, rate, budget_per_hour, model_dir, device=device,
                             budget=budget))
        det = tuned.detector
        t1 = time.perf_counter()
        s = det.decision_function(test)
        t2 = time.perf_counter()
        args = (test.flight_id.to_numpy(), test.t.to_numpy(), test.label.to_numpy(), s)
        alarms = s > det.threshold_
        res = evaluate(*args, alarms, gps_rate_hz=rate, offsets=offsets)
        at_budget = evaluate(*args, s > det.budget_threshold_, gps_rate_hz=rate, offsets=offsets, vus=False)
        res.update(onset_and_types(det, test, alarms, typer, typed))
        res["event_recall_by_type"] = event_recall_by_type(args[0], args[2], alarms, true_types)
        ci = bootstrap_f1(args[0], args[2], alarms, n_boot=N_BOOTSTRAP, seed=seed)
        res["f1_ci95"] = list(ci) if ci is not None else None
        if detectors is not None:
            detectors[m] = det
        out[m] = {**res, "threshold": det.threshold_, "params": tuned.params, "val_f1": tuned.val_f1,
                  "budget": {**at_budget, "threshold": det.budget_threshold_,
                             "alarms_per_hour_allowed": budget_per_hour},
                  "tune_seconds": t1 - t0, "score_seconds": t2 - t1, "model_from_cache": tuned.cached}
        unit = (tuning or {}).get(m)
        if unit is not None:
            out[m]["model_from_cache"] = bool(unit["cached"])
            if not unit["cached"]:
                out[m]["tune_seconds"] = unit["seconds"]
        scores[f"score_{m}"] = s
        scores[f"alarm_{m}"] = alarms.astype(np.int8)
        alerts.append(alerts_frame(alerts_from_scores(test, s, det, typer=typer, memo=typed)).assign(method=m))
    return {"split": split, "methods": out, "alerts": pd.concat(alerts, ignore_index=True) if alerts else None}, scores


def training_budget_doc(budget: TrainingBudget | None, methods: list[str]) -> dict[str, Any]:
    """What results.json records of the training budget: ``full`` (the methods' defaults) or
    the reduced budget's rule and each method's scaled parameters."""
    if budget is None:
        return {"name": "full"}
    return {**budget.describe(), "per_method": {m: budget.fixed(m) for m in methods}}


def onset_and_types(det, test: pd.DataFrame, alarms: np.ndarray,
                    typer: ShapeTyper | None = None, typed: dict[int, str] | None = None) -> dict[str, Any]:
    """For detectors that estimate onsets: onset error of each detected window (estimated
    minus true onset, s). Confusion counts of the attack type at each alarm run against the
    true type at its first alarm (``none`` for a false alarm): ``type_confusion``, the
    detector's own type at the first alarm (``attack`` from a detector that does not
    classify); with a ``typer`` (X carrying the columns it reads), the typer's type at the first
    alarm (``type_confusion_shape``) and confirmed ``typer.confirm_s`` later
    (``type_confusion_shape_confirmed``). ``attack_typing``: per detected attack
    (``detected_attacks``), how many are typed right (``own``: by the detector's classifier,
    None if it has none; ``shape_first``, ``shape_confirmed``: by the typer at the first alarm
    on the attack and ``confirm_s`` later). ``typed``: row -> type already found for these
    rows (shared between detectors scored on the same flights)."""
    out: dict[str, Any] = {}
    if hasattr(det, "onset_times"):
        # attack windows (first and last attacked times) per flight, computed once
        windows: dict[Any, list[tuple[float, float]]] = {}
        for fid, g in test.groupby("flight_id", sort=False):
            t = g.t.to_numpy()
            windows[fid] = [(t[s], t[e - 1]) for s, e in runs(g.label.to_numpy() == 1)]
        errors = []
        for fid, t_alarm, t_onset in det.onset_times(test, alarms):
            # the window this alarm falls in (none: a false alarm, no onset error)
            errors += [t_onset - s0 for s0, e0 in windows.get(fid, []) if s0 <= t_alarm <= e0]
        out["onset_error_median_s"] = float(np.median(errors)) if errors else None
        out["onset_error_p95_s"] = float(np.percentile(np.abs(errors), 95)) if errors else None
    true = np.where(test.label.to_numpy() == 1, test.attack_type.astype(str).to_numpy(), "none")
    first = np.flatnonzero(run_starts(test, alarms))
    own = hasattr(det, "predict_type")
    pred = det.predict_type(test) if own else np.full(len(test), "attack", dtype=object)
    out["type_confusion"] = confusion(true[first], pred[first])
    # per detected attack: its first alarm on an attacked step
    a_first = detected_attacks(test, alarms)
    typing = {"own": right_count(true[a_first], pred[a_first]) if own else None}
    if typer is not None:
        out["type_confusion_shape"] = confusion(true[first], typer.type_rows(test, first, typed))
        out["type_confusion_shape_confirmed"] = confusion(
            true[first], typer.type_rows(test, typer.confirm_rows(test, first), typed))
        typing["shape_first"] = right_count(true[a_first], typer.type_rows(test, a_first, typed))
        typing["shape_confirmed"] = right_count(
            true[a_first], typer.type_rows(test, typer.confirm_rows(test, a_first), typed))
    out["attack_typing"] = typing
    return out


def detected_attacks(X: pd.DataFrame, alarms: np.ndarray) -> np.ndarray:
    """Rows of the first alarm on an attacked step of each flight that has one: one per detected
    attack (a flight holds at most one attack)."""
    hit = np.asarray(alarms, dtype=bool) & (X["label"].to_numpy() == 1)
    return np.array([int(idx[np.argmax(hit[idx])]) for _, idx in flight_slices(X) if hit[idx].any()], dtype=int)


def right_count(true, pred) -> dict[str, int]:
    """How many of the types ``pred`` equal ``true``: {"right", "attacks"}."""
    true, pred = np.asarray(true, dtype=str), np.asarray(pred, dtype=str)
    return {"right": int((true == pred).sum()), "attacks": int(len(true))}


def confusion(true, pred) -> dict[str, dict[str, int]]:
    """Counts {true type: {predicted type: n}}."""
    conf: dict[str, dict[str, int]] = {}
    for tt, pp in zip(true, pred):
        row = conf.setdefault(str(tt), {})
        row[str(pp)] = row.get(str(pp), 0) + 1
    return conf


def run_benchmark(profile: str | Profile, methods: list[str], out: Path, cache_dir: Path,
                  progress: bool = True, workers: int | None = None, seed: int = 0,
                  label_fraction: float = 0.2, budget_per_hour: float = 1.0, stress: bool = False,
                  backend: Backend | None = None, device: str = "auto") -> dict[str, Any]:
    """Every method on the profile's configurations (datasets and tuned detectors cached).

    Work units on ``backend`` (default: local processes): one per dataset to simulate, then one
    per (configuration, method) to tune; the test flights are then scored here, with the
    tuned detectors read from the cache, so the figures do not depend on the backend.
    stress: also score the tuned detectors on each configuration's stress datasets
    (``experiments.stress``; simulated and cached like the others), under ``results["stress"]``.
    device: where network detectors train (``auto``: a GPU when the worker has one)."""
    from quadformer.experiments.stress import stress_configs

    prof = get_profile(profile)
    for m in methods:
        get(m)   # unknown names fail before any work
    check_device(device, backend, workers)   # an unavailable GPU fails before any work
    t_start = time.perf_counter()
    configs = profile_configs(prof)
    stress_units = {name: stress_configs(name, cfg, prof.stress_flights) for name, cfg in configs} if stress else {}
    paths = ensure_configs(configs + [(n, c) for units in stress_units.values() for n, _, c in units], cache_dir,
                           progress=progress, workers=workers, backend=backend)
    t_sim = time.perf_counter() - t_start
    items = [(name, paths[name], model_dir_for(cache_dir, paths[name], seed, label_fraction),
              {"model": model, "noise": noise, "attack": attack})
             for (model, noise, attack), (name, _) in zip(prof.grid, configs)]
    t0 = time.perf_counter()
    tuning = ensure_tuned([(name, path, model_dir) for name, path, model_dir, _ in items], methods, seed,
                          label_fraction, budget_per_hour, device=device, progress=progress, workers=workers,
                          backend=backend, budget=prof.budget)
    t_tune = time.perf_counter() - t0
    head = {"profile": prof.name, "flights_per_config": prof.flights, "duration_s": prof.duration,
            "dataset_seed": prof.seed, "training_budget": training_budget_doc(prof.budget, methods)}
    stress_items = {name: [(n, st, paths[n], c.seed) for n, st, c in units] for name, units in stress_units.items()}
    if stress:
        head["stress_flights_per_set"] = prof.stress_flights
    return _evaluate(items, methods, Path(out), head, t_start, t_sim, progress, seed, label_fraction,
                     budget_per_hour, stress=stress_items if stress else None, tuning=tuning, t_tune=t_tune,
                     budget=prof.budget)


def run_shipped(profile: str | Profile, shipped: dict[str, str], out: Path, cache_dir: Path, progress: bool = True,
                workers: int | None = None) -> dict[str, Any]:
    """The shipped detectors (method -> shipped name) on the profile's configurations, every
    flight a test flight; nothing tuned. The profile's seed must not be the zoo's."""
    prof = get_profile(profile)
    if prof.seed == ZOO_SEED:
        raise ValueError(f"profile seed {prof.seed} is the zoo's: its flights are the shipped detectors' own")
    t_start = time.perf_counter()
    configs = profile_configs(prof)
    paths = ensure_configs(configs, cache_dir, progress=progress, workers=workers)
    t_sim = time.perf_counter() - t_start
    items = [(name, paths[name], None, {"model": model, "noise": noise, "attack": attack})
             for (model, noise, attack), (name, _) in zip(prof.grid, configs)]
    head = {"profile": prof.name, "flights_per_config": prof.flights, "duration_s": prof.duration,
            "dataset_seed": prof.seed, "shipped": shipped,
            "training_budget": {"name": "shipped", "rule": "the shipped detectors' own (full budgets; "
                                "`quadformer zoo show NAME`)"}}
    methods = list(shipped)
    return _evaluate(items, methods, Path(out), head, t_start, t_sim, progress, 0, 0.2, 1.0, shipped=shipped,
                     workers=workers)


def run_datasets(paths: list[Path], methods: list[str], out: Path, progress: bool = True, seed: int = 0,
                 label_fraction: float = 0.2, budget_per_hour: float = 1.0, device: str = "auto") -> dict[str, Any]:
    """Every method on given datasets (simulated, or imported from flight logs), same protocol;
    detectors are tuned afresh (no cache), here in this process."""
    from quadformer.detectors.neural import resolve_device

    device = resolve_device(device)
    for m in methods:
        get(m)
    for p in paths:
        load_dataset(p)   # a missing or corrupt dataset fails before any work
    names = [Path(p).name for p in paths]
    if len(set(names)) != len(names):
        raise ValueError(f"datasets must have distinct directory names, got {', '.join(names)}")
    items = [(name, Path(p), None, {}) for name, p in zip(names, paths)]
    head = {"profile": None, "datasets": [str(p) for p in paths]}
    return _evaluate(items, methods, Path(out), head, time.perf_counter(), 0.0, progress, seed, label_fraction,
                     budget_per_hour, device=device)


def _score_shipped(path: Path, methods: list[str], budget_per_hour: float,
                   shipped: dict[str, str]) -> tuple[dict[str, Any], pd.DataFrame]:
    """One work unit: ``run_config`` of the shipped detectors on the dataset at ``path``."""
    return run_config(load_dataset(path), methods, budget_per_hour=budget_per_hour, shipped=shipped)


def _evaluate(items, methods, out: Path, head: dict[str, Any], t_start: float, t_sim: float, progress: bool,
              seed: int, label_fraction: float, budget_per_hour: float,
              stress: dict[str, list] | None = None, tuning: dict[tuple[str, str], dict[str, Any]] | None = None,
              t_tune: float | None = None, device: str | None = None,
              budget: TrainingBudget | None = None, shipped: dict[str, str] | None = None,
              workers: int | None = None) -> dict[str, Any]:
    """Tune and score every method on each (name, dataset path, model cache, description);
    with ``stress`` (configuration name -> [(dataset name, stress set, path, seed)]) score the
    tuned detectors on those datasets too; write results.json, scores, alerts and the report.
    With ``shipped`` detectors (nothing to tune) the configurations are scored in ``workers``
    processes (default one per core), each configuration one unit."""
    from quadformer.experiments.stress import StressPool, score_stress, stress_sets_doc
    from quadformer.report import write_report

    (out / "scores").mkdir(parents=True, exist_ok=True)
    configs = []
    all_alerts: list[pd.DataFrame] = []
    iterator = items
    shared = progress if isinstance(progress, SharedBar) else None
    scored: dict[str, tuple[dict[str, Any], pd.DataFrame]] = {}
    if shipped is not None and stress is None and len(items) > 1 and batch_count(workers) > 1:
        outs = run_jobs(_score_shipped, [(path, methods, budget_per_hour, shipped) for _, path, _, _ in items],
                        workers=workers, progress=progress, desc="evaluate", unit="dataset",
                        labels=[name for name, *_ in items])
        scored = {name: o for (name, *_), o in zip(items, outs)}
    elif shared is not None:
        shared.phase("evaluate")
    elif progress:
        from tqdm.auto import tqdm
        iterator = tqdm(items, desc="evaluate", unit="dataset")
    pool = StressPool()
    stress_out: dict[str, Any] = {}
    t_stress, rate = 0.0, 10.0
    for name, path, model_dir, described in iterator:
        ds = load_dataset(path)
        rate = ds.gps_rate_hz
        tuned: dict[str, Any] = {}
        res, scores = scored[name] if name in scored else run_config(
            ds, methods, seed=seed, label_fraction=label_fraction, budget_per_hour=budget_per_hour,
            model_dir=model_dir, detectors=tuned, device=device,
            tuning={m: tuning[(name, m)] for m in methods} if tuning else None, budget=budget, shipped=shipped)
        t0 = time.perf_counter()
        for ds_name, st, st_path, st_seed in (stress or {}).get(name, []):
            stress_out.setdefault(name, {})[st.name] = {
                "dataset": str(st_path), "dataset_seed": st_seed,
                "methods": score_stress(tuned, load_dataset(st_path), st.name, pool)}
        t_stress += time.perf_counter() - t0
        with atomic_path(out / "scores" / f"{name}.parquet") as tmp:
            scores.to_parquet(tmp, index=False)
        frame = res.pop("alerts")
        if frame is not None:
            all_alerts.append(frame.assign(config=name))
        configs.append({"name": name, **described, "dataset": str(path), "n_test_flights": res["split"]["test"],
                        **res})
        if shared is not None and name not in scored:
            shared.update(1)
    results = {
        **head, "seed": seed, "label_fraction": label_fraction, "methods_run": methods,
        "protocol": ("split by flight 60/20/20 (stratified), hyper-parameters and threshold maximise "
                     "validation point-wise F1; test scored once; no point adjustment" if shipped is None else
                     "shipped detectors (tuned and calibrated on the zoo's own simulated flights, seed "
                     f"{ZOO_SEED}); every flight of these datasets is a new test flight; thresholds: the shipped "
                     "validation-F1 ones (and the budget ones); no point adjustment"),
        "configs": configs, "versions": package_versions(),
        "provenance": provenance({**({"dataset": head["dataset_seed"]} if "dataset_seed" in head else {}),
                                  **({"split": seed} if shipped is None else {})}, head.get("profile")),
        "timing_s": {"simulate": t_sim, "total": time.perf_counter() - t_start},
    }
    if t_tune is not None:
        results["timing_s"]["tune"] = t_tune
    if stress is not None:
        results["stress"] = {
            "flights_per_set": head.get("stress_flights_per_set"),
            "protocol": "detectors tuned as in the main run (same datasets, split and tuned-model cache), "
                        "thresholds from validation flights; every flight of a stress dataset is a test flight",
            "sets": stress_sets_doc(), "configs": stress_out, "pooled": pool.results(rate),
        }
        results["timing_s"]["stress_scoring"] = t_stress
    if all_alerts:    # every method's alerts on the test flights
        with atomic_path(out / "alerts.csv") as tmp:
            pd.concat(all_alerts, ignore_index=True).to_csv(tmp, index=False)
    write_json(out / "results.json", results)
    write_report(results, out)
    return results
