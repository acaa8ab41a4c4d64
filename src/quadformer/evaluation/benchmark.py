"""The benchmark: the paper's eight configurations, every method, one protocol.

Datasets are cached by their full configuration (a hash of the resolved SimConfig), so a
second run reuses them. For each configuration and method the protocol of
``evaluation.protocol`` picks hyper-parameters and threshold on validation flights; the
test flights are scored once.
"""

from __future__ import annotations

import functools
import hashlib
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from quadformer.config import SimConfig
from quadformer.evaluation.metrics import evaluate
from quadformer.evaluation.protocol import Tuned, split_flights, training_labels, tune
from quadformer.resilience.alerts import alerts_frame, alerts_from_scores
from quadformer.simulation.dataset import FORMAT_VERSION, Dataset, DatasetError, load_dataset, package_versions
from quadformer.simulation.grid import PAPER_GRID, config_name, grid_config, simulate_jobs


@dataclass(frozen=True)
class Profile:
    name: str
    flights: int            # per configuration
    duration: float = 60.0  # s per flight
    seed: int = 0


PROFILES = {
    "demo": Profile("demo", 20),
    "quick": Profile("quick", 60),
    "paper": Profile("paper", 600),
}


def profile_configs(profile: Profile) -> list[tuple[str, SimConfig]]:
    base = SimConfig(flights=profile.flights, duration=profile.duration, seed=profile.seed)
    return [(config_name(*c), grid_config(base, *c)) for c in PAPER_GRID]


def dataset_key(cfg: SimConfig) -> str:
    d = cfg.to_dict()
    d.pop("batch_size", None)   # does not change the data
    d["format_version"] = FORMAT_VERSION   # what the simulator writes
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


def ensure_datasets(profile: Profile, cache_dir: Path, progress: bool = True,
                    workers: int | None = None) -> dict[str, Path]:
    """Paths of the profile's datasets, simulating those not in the cache."""
    cache_dir = Path(cache_dir)
    paths, jobs = {}, []
    for name, cfg in profile_configs(profile):
        path = cache_dir / f"{name}-{dataset_key(cfg)}"
        paths[name] = path
        try:
            load_dataset(path)
        except DatasetError:
            jobs.append((name, cfg, path))
    simulate_jobs(jobs, progress=progress, overwrite=True, workers=workers)
    return paths


@functools.lru_cache(maxsize=1)
def _detectors_digest() -> str:
    """Hash of the detector code: a tuned model cached by an older version is not reused."""
    import quadformer.detectors as pkg
    h = hashlib.sha256()
    for f in sorted(Path(pkg.__file__).parent.rglob("*.py")):
        h.update(f.read_bytes())
    return h.hexdigest()[:12]


def tuned_model(method: str, train: pd.DataFrame, y_train: np.ndarray, val: pd.DataFrame, rate: float,
                budget_per_hour: float, model_dir: Path | None) -> Tuned:
    """``protocol.tune``, cached in ``model_dir`` (one dataset, split and label set per directory):
    the detection and resilience benchmarks share tuned detectors instead of training twice."""
    if model_dir is None:
        return tune(method, train, y_train, val, gps_rate_hz=rate, budget_per_hour=budget_per_hour)
    from quadformer.detectors import load
    base = Path(model_dir) / f"{method}-b{budget_per_hour:g}-{_detectors_digest()}"
    meta_path = base.with_suffix(".tuned.json")
    if meta_path.exists():
        try:
            meta = json.loads(meta_path.read_text())
            det = load(base.with_suffix(".json"))
            return Tuned(det, meta["params"], meta["threshold"], meta["val_f1"], meta["budget_threshold"],
                         meta["grid"], cached=True)
        except (OSError, ValueError, KeyError):
            pass   # unreadable cache entry: tune again and overwrite it
    tuned = tune(method, train, y_train, val, gps_rate_hz=rate, budget_per_hour=budget_per_hour)
    base.parent.mkdir(parents=True, exist_ok=True)
    tuned.detector.save(base.with_suffix(".json"))
    tmp = meta_path.with_name(meta_path.name + ".tmp")
    tmp.write_text(json.dumps({"params": tuned.params, "threshold": tuned.threshold, "val_f1": tuned.val_f1,
                               "budget_threshold": tuned.budget_threshold, "grid": tuned.grid}, default=float))
    tmp.replace(meta_path)
    return tuned


def model_dir_for(cache_dir: Path, dataset_path: Path, seed: int, label_fraction: float) -> Path:
    """Where tuned detectors of one dataset, split seed and label fraction are cached."""
    return Path(cache_dir) / "models" / f"{Path(dataset_path).name}-s{seed}-l{label_fraction:g}"


def run_config(ds: Dataset, methods: list[str], seed: int = 0, label_fraction: float = 0.2,
               budget_per_hour: float = 1.0, model_dir: Path | None = None) -> tuple[dict[str, Any], pd.DataFrame]:
    """Tune and evaluate every method on one dataset. Returns (results, per-step test scores).

    model_dir: cache of tuned detectors (see ``tuned_model``); None: always tune."""
    cfg = ds.config
    rate = cfg.gps.rate_hz
    f = ds.flights
    sp = split_flights(ds.scenarios, seed, label_fraction=label_fraction)
    train = f[f.flight_id.isin(sp.train)].reset_index(drop=True)
    val = f[f.flight_id.isin(sp.val)].reset_index(drop=True)
    test = f[f.flight_id.isin(sp.test)].reset_index(drop=True)
    y_train = training_labels(train, sp.labelled)
    offsets = np.linalg.norm(test[["atk_d_x", "atk_d_y", "atk_d_z"]].to_numpy(), axis=1)
    scores = test[["flight_id", "t", "label"]].copy()
    out: dict[str, Any] = {}
    alerts: list[pd.DataFrame] = []
    for m in methods:
        t0 = time.perf_counter()
        tuned = tuned_model(m, train, y_train, val, rate, budget_per_hour, model_dir)
        t1 = time.perf_counter()
        s = tuned.detector.decision_function(test)
        t2 = time.perf_counter()
        args = (test.flight_id.to_numpy(), test.t.to_numpy(), test.label.to_numpy(), s)
        res = evaluate(*args, s > tuned.threshold, gps_rate_hz=rate, offsets=offsets)
        at_budget = evaluate(*args, s > tuned.budget_threshold, gps_rate_hz=rate, offsets=offsets)
        res.update(onset_and_types(tuned.detector, test, s > tuned.threshold))
        out[m] = {**res, "threshold": tuned.threshold, "params": tuned.params, "val_f1": tuned.val_f1,
                  "budget": {**at_budget, "threshold": tuned.budget_threshold,
                             "alarms_per_hour_allowed": budget_per_hour},
                  "tune_seconds": t1 - t0, "score_seconds": t2 - t1, "model_from_cache": tuned.cached}
        scores[f"score_{m}"] = s
        scores[f"alarm_{m}"] = (s > tuned.threshold).astype(np.int8)
        alerts.append(alerts_frame(alerts_from_scores(test, s, tuned.threshold, tuned.detector)).assign(method=m))
    split = {"train": len(sp.train), "val": len(sp.val), "test": len(sp.test), "labelled": len(sp.labelled)}
    return {"split": split, "methods": out, "alerts": pd.concat(alerts, ignore_index=True) if alerts else None}, scores


def onset_and_types(det, test: pd.DataFrame, alarms: np.ndarray) -> dict[str, Any]:
    """For detectors that estimate onsets and attack types: onset error of each detected
    window (estimated minus true onset, s) and a confusion count of the type predicted at the
    first alarm of each alarm run (true type ``none`` for a false alarm)."""
    out: dict[str, Any] = {}
    if hasattr(det, "onset_times"):
        # attack windows (start, end times) per flight, computed once
        windows: dict[Any, list[tuple[float, float]]] = {}
        for fid, g in test.groupby("flight_id", sort=False):
            lab, t = g.label.to_numpy() == 1, g.t.to_numpy()
            windows[fid] = list(zip(t[lab & ~np.r_[False, lab[:-1]]], t[lab & ~np.r_[lab[1:], False]]))
        errors = []
        for fid, t_alarm, t_onset in det.onset_times(test, alarms):
            # the window this alarm falls in (none: a false alarm, no onset error)
            errors += [t_onset - s0 for s0, e0 in windows.get(fid, []) if s0 <= t_alarm <= e0]
        out["onset_error_median_s"] = float(np.median(errors)) if errors else None
        out["onset_error_p95_s"] = float(np.percentile(np.abs(errors), 95)) if errors else None
    if hasattr(det, "predict_type"):
        pred = det.predict_type(test)
        true = np.where(test.label.to_numpy() == 1, test.attack_type.astype(str).to_numpy(), "none")
        a = np.asarray(alarms, bool)
        first = a & ~np.r_[False, a[:-1]] | (a & (test.flight_id.to_numpy() != np.r_[-1, test.flight_id.to_numpy()[:-1]]))
        conf: dict[str, dict[str, int]] = {}
        for tt, pp in zip(true[first], pred[first]):
            conf.setdefault(tt, {}).setdefault(str(pp), 0)
            conf[tt][str(pp)] += 1
        out["type_confusion"] = conf
    return out


def run_benchmark(profile: str | Profile, methods: list[str], out: Path, cache_dir: Path,
                  progress: bool = True, workers: int | None = None, seed: int = 0,
                  label_fraction: float = 0.2, budget_per_hour: float = 1.0) -> dict[str, Any]:
    from quadformer.detectors import get
    from quadformer.report import write_report

    prof = PROFILES[profile] if isinstance(profile, str) else profile
    for m in methods:
        get(m)   # unknown names fail before any work
    out = Path(out)
    t_start = time.perf_counter()
    paths = ensure_datasets(prof, cache_dir, progress=progress, workers=workers)
    t_sim = time.perf_counter() - t_start
    (out / "scores").mkdir(parents=True, exist_ok=True)
    configs = []
    all_alerts: list[pd.DataFrame] = []
    items = list(zip(PAPER_GRID, paths.items()))
    iterator = items
    if progress:
        from tqdm.auto import tqdm
        iterator = tqdm(items, desc="evaluate", unit="config")
    for (model, noise, attack), (name, path) in iterator:
        ds = load_dataset(path)
        res, scores = run_config(ds, methods, seed=seed, label_fraction=label_fraction,
                                 budget_per_hour=budget_per_hour,
                                 model_dir=model_dir_for(cache_dir, path, seed, label_fraction))
        scores.to_parquet(out / "scores" / f"{name}.parquet", index=False)
        frame = res.pop("alerts")
        if frame is not None:
            all_alerts.append(frame.assign(config=name))
        configs.append({"name": name, "model": model, "noise": noise, "attack": attack,
                        "dataset": str(path), "n_test_flights": res["split"]["test"], **res})
    results = {
        "profile": prof.name, "flights_per_config": prof.flights, "duration_s": prof.duration,
        "seed": seed, "label_fraction": label_fraction, "methods_run": methods,
        "protocol": "split by flight 60/20/20 (stratified), hyper-parameters and threshold maximise "
                    "validation point-wise F1; test scored once; no point adjustment",
        "configs": configs, "versions": package_versions(),
        "timing_s": {"simulate": t_sim, "total": time.perf_counter() - t_start},
    }
    if all_alerts:    # every method's alerts on the test flights
        tmp = out / "alerts.csv.tmp"
        pd.concat(all_alerts, ignore_index=True).to_csv(tmp, index=False)
        tmp.replace(out / "alerts.csv")
    tmp = out / "results.json.tmp"
    tmp.write_text(json.dumps(results, indent=2, default=float))
    tmp.replace(out / "results.json")
    write_report(results, out)
    return results
