"""The detection benchmark: the paper's eight configurations, every method, one protocol.

For each configuration and method the protocol of ``evaluation.protocol`` picks
hyper-parameters and threshold on validation flights; the test flights are scored once.
Datasets and tuned detectors come from the caches of ``experiments.cache``.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from quadformer.dataset import Dataset, load_dataset
from quadformer.detectors import alerts_frame, alerts_from_scores, get, runs
from quadformer.detectors.alarms import run_starts
from quadformer.evaluation.metrics import evaluate
from quadformer.evaluation.protocol import split_flights
from quadformer.experiments.cache import ensure_datasets, model_dir_for, tuned_model
from quadformer.experiments.grid import PAPER_GRID, Profile, get_profile
from quadformer.io import atomic_path, package_versions, write_json


def run_config(ds: Dataset, methods: list[str], seed: int = 0, label_fraction: float = 0.2,
               budget_per_hour: float = 1.0, model_dir: Path | None = None) -> tuple[dict[str, Any], pd.DataFrame]:
    """Tune and evaluate every method on one dataset. Returns (results, per-step test scores).

    model_dir: cache of tuned detectors (see ``tuned_model``); None: always tune."""
    rate = ds.gps_rate_hz
    sp = split_flights(ds.scenarios, seed, label_fraction=label_fraction)
    parts = sp.frames(ds.flights)
    test = parts.test
    offsets = np.linalg.norm(test[["atk_d_x", "atk_d_y", "atk_d_z"]].to_numpy(), axis=1)
    scores = test[["flight_id", "t", "label"]].copy()
    out: dict[str, Any] = {}
    alerts: list[pd.DataFrame] = []
    for m in methods:
        t0 = time.perf_counter()
        tuned = tuned_model(m, parts.train, parts.y_train, parts.val, rate, budget_per_hour, model_dir)
        det = tuned.detector
        t1 = time.perf_counter()
        s = det.decision_function(test)
        t2 = time.perf_counter()
        args = (test.flight_id.to_numpy(), test.t.to_numpy(), test.label.to_numpy(), s)
        alarms = s > det.threshold_
        res = evaluate(*args, alarms, gps_rate_hz=rate, offsets=offsets)
        at_budget = evaluate(*args, s > det.budget_threshold_, gps_rate_hz=rate, offsets=offsets)
        res.update(onset_and_types(det, test, alarms))
        out[m] = {**res, "threshold": det.threshold_, "params": tuned.params, "val_f1": tuned.val_f1,
                  "budget": {**at_budget, "threshold": det.budget_threshold_,
                             "alarms_per_hour_allowed": budget_per_hour},
                  "tune_seconds": t1 - t0, "score_seconds": t2 - t1, "model_from_cache": tuned.cached}
        scores[f"score_{m}"] = s
        scores[f"alarm_{m}"] = alarms.astype(np.int8)
        alerts.append(alerts_frame(alerts_from_scores(test, s, det)).assign(method=m))
    split = {"train": len(sp.train), "val": len(sp.val), "test": len(sp.test), "labelled": len(sp.labelled)}
    return {"split": split, "methods": out, "alerts": pd.concat(alerts, ignore_index=True) if alerts else None}, scores


def onset_and_types(det, test: pd.DataFrame, alarms: np.ndarray) -> dict[str, Any]:
    """For detectors that estimate onsets and attack types: onset error of each detected
    window (estimated minus true onset, s) and a confusion count of the type predicted at the
    first alarm of each alarm run (true type ``none`` for a false alarm)."""
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
    if hasattr(det, "predict_type"):
        pred = det.predict_type(test)
        true = np.where(test.label.to_numpy() == 1, test.attack_type.astype(str).to_numpy(), "none")
        first = run_starts(test, alarms)
        conf: dict[str, dict[str, int]] = {}
        for tt, pp in zip(true[first], pred[first]):
            conf.setdefault(tt, {}).setdefault(str(pp), 0)
            conf[tt][str(pp)] += 1
        out["type_confusion"] = conf
    return out


def run_benchmark(profile: str | Profile, methods: list[str], out: Path, cache_dir: Path,
                  progress: bool = True, workers: int | None = None, seed: int = 0,
                  label_fraction: float = 0.2, budget_per_hour: float = 1.0) -> dict[str, Any]:
    """Every method on the profile's eight configurations (datasets and tuned detectors cached)."""
    prof = get_profile(profile)
    for m in methods:
        get(m)   # unknown names fail before any work
    t_start = time.perf_counter()
    paths = ensure_datasets(prof, cache_dir, progress=progress, workers=workers)
    t_sim = time.perf_counter() - t_start
    items = [(name, path, model_dir_for(cache_dir, path, seed, label_fraction),
              {"model": model, "noise": noise, "attack": attack})
             for (model, noise, attack), (name, path) in zip(PAPER_GRID, paths.items())]
    head = {"profile": prof.name, "flights_per_config": prof.flights, "duration_s": prof.duration}
    return _evaluate(items, methods, Path(out), head, t_start, t_sim, progress, seed, label_fraction,
                     budget_per_hour)


def run_datasets(paths: list[Path], methods: list[str], out: Path, progress: bool = True, seed: int = 0,
                 label_fraction: float = 0.2, budget_per_hour: float = 1.0) -> dict[str, Any]:
    """Every method on given datasets (simulated, or imported from flight logs), same protocol;
    detectors are tuned afresh (no cache)."""
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
                     budget_per_hour)


def _evaluate(items, methods, out: Path, head: dict[str, Any], t_start: float, t_sim: float, progress: bool,
              seed: int, label_fraction: float, budget_per_hour: float) -> dict[str, Any]:
    """Tune and score every method on each (name, dataset path, model cache, description);
    write results.json, scores, alerts and the report."""
    from quadformer.report import write_report

    (out / "scores").mkdir(parents=True, exist_ok=True)
    configs = []
    all_alerts: list[pd.DataFrame] = []
    iterator = items
    if progress:
        from tqdm.auto import tqdm
        iterator = tqdm(items, desc="evaluate", unit="dataset")
    for name, path, model_dir, described in iterator:
        ds = load_dataset(path)
        res, scores = run_config(ds, methods, seed=seed, label_fraction=label_fraction,
                                 budget_per_hour=budget_per_hour, model_dir=model_dir)
        with atomic_path(out / "scores" / f"{name}.parquet") as tmp:
            scores.to_parquet(tmp, index=False)
        frame = res.pop("alerts")
        if frame is not None:
            all_alerts.append(frame.assign(config=name))
        configs.append({"name": name, **described, "dataset": str(path), "n_test_flights": res["split"]["test"],
                        **res})
    results = {
        **head, "seed": seed, "label_fraction": label_fraction, "methods_run": methods,
        "protocol": "split by flight 60/20/20 (stratified), hyper-parameters and threshold maximise "
                    "validation point-wise F1; test scored once; no point adjustment",
        "configs": configs, "versions": package_versions(),
        "timing_s": {"simulate": t_sim, "total": time.perf_counter() - t_start},
    }
    if all_alerts:    # every method's alerts on the test flights
        with atomic_path(out / "alerts.csv") as tmp:
            pd.concat(all_alerts, ignore_index=True).to_csv(tmp, index=False)
    write_json(out / "results.json", results)
    write_report(results, out)
    return results
