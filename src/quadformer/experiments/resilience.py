"""The resilience benchmark: closed-loop flights under four GPS admission policies.

For each of the paper's eight configurations: the detector is tuned exactly as in the
detection benchmark (train/validation flights of the cached dataset), then the *test*
flights are flown again in closed loop, once per policy, in one batch: same missions,
wind, sensor noise and attacks (flight i's randomness depends only on the configuration,
its seed and i), so the policies differ only in how they fuse GPS. The naive policy
reproduces the dataset's flights. Metrics: ``evaluation.resilience``, among them the detection
in the closed loop: point-wise precision, recall and F1 of "GPS excluded" against "GPS spoofed".
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from quadformer.dataset import Dataset, load_dataset
from quadformer.detectors import StreamGroup, alerts_frame, alerts_from_scores, get
from quadformer.detectors.alarms import ALERT_COLUMNS
from quadformer.detectors.attack_types import alert_typer
from quadformer.estimator.schema import GROUPS, RESIDUES
from quadformer.evaluation.protocol import TrainingBudget, split_flights
from quadformer.evaluation.resilience import flight_metrics, summarize_policy
from quadformer.experiments.cache import (batch_count, check_device, ensure_datasets, ensure_tuned, model_dir_for,
                                         tuned_model)
from quadformer.experiments.detection import training_budget_doc
from quadformer.experiments.grid import Profile, get_profile, profile_configs
from quadformer.experiments.zoo import shipped_tuned
from quadformer.experiments.pool import Backend, run_jobs
from quadformer.experiments.provenance import provenance
from quadformer.io import atomic_path, package_versions, write_json
from quadformer.resilience import POLICIES, READMIT_CLEAR, READMIT_STALE, Admission, AdmissionConfig
from quadformer.config import SimConfig
from quadformer.simulation import mixable_families, simulate_groups

THRESHOLDS = ("f1", "budget")


def run_config(ds: Dataset, detector: str, seed: int = 0, label_fraction: float = 0.2,
               policies: tuple[str, ...] = POLICIES, admission: AdmissionConfig | None = None,
               max_flights: int | None = None, model_dir: Path | None = None, threshold: str = "f1",
               budget: TrainingBudget | None = None) -> tuple[dict[str, Any], pd.DataFrame, pd.DataFrame]:
    """Tune ``detector`` on the dataset's train/validation flights (or load it from
    ``model_dir``, the detection benchmark's cache) and fly its test flights under every
    policy. Returns (results, per-step trajectories, alerts of the resilient policy).

    threshold: the detector's alarm threshold, both chosen on validation flights: ``f1``
    maximises validation F1 (the detection benchmark's), ``budget`` allows one alarm per
    flight-hour on clean validation flights (fewer wrongful exclusions, later detections)."""
    return run_configs([(ds, model_dir)], detector, seed, label_fraction, policies, admission, max_flights,
                       threshold, budget)[0]


def run_configs(parts: list[tuple[Dataset, Path | None]], detector: str, seed: int = 0, label_fraction: float = 0.2,
                policies: tuple[str, ...] = POLICIES, admission: AdmissionConfig | None = None,
                max_flights: int | None = None, threshold: str = "f1",
                budget: TrainingBudget | None = None,
                shipped: str | None = None) -> list[tuple[dict[str, Any], pd.DataFrame, pd.DataFrame]]:
    """``run_config`` for several configurations (``parts``: dataset and model cache per
    configuration, the configurations ``simulation.mixable``) flown in one closed-loop batch,
    each configuration's flights driven by the detector tuned on it. Each configuration's
    results equal those of ``run_config`` alone (flight i's randomness depends only on its
    configuration, seed and i; each detector streams over its own flights); ``fly_seconds``
    is the shared batch's time. ``shipped``: a shipped detector's name drives every
    configuration instead (nothing tuned; every flight of the datasets is a test flight)."""
    if threshold not in THRESHOLDS:
        raise ValueError(f"threshold: unknown choice {threshold!r}; choose from {', '.join(THRESHOLDS)}")
    plans = [_plan(ds, model_dir, detector, seed, label_fraction, policies, max_flights, threshold, budget, shipped)
             for ds, model_dir in parts]
    rate = plans[0]["cfg"].gps.rate_hz
    adm = Admission(np.concatenate([p["pol"] for p in plans]), rate, admission)
    stream = StreamGroup([p["det"].stream(len(p["flights"])) for p in plans])
    t0 = time.perf_counter()
    flown = simulate_groups([(p["cfg"], p["flights"], p["attacked"]) for p in plans], admission=adm, stream=stream)
    t_fly = time.perf_counter() - t0
    return [_outcome(p, r, detector, threshold, policies, t_fly) for p, r in zip(plans, flown)]


def _plan(ds: Dataset, model_dir: Path | None, detector: str, seed: int, label_fraction: float,
          policies: tuple[str, ...], max_flights: int | None, threshold: str,
          budget: TrainingBudget | None, shipped: str | None = None) -> dict[str, Any]:
    """One configuration's part of a closed-loop batch: its tuned detector and the test
    flights to fly under every policy."""
    cfg = ds.config
    t0 = time.perf_counter()
    if shipped is None:
        sp = split_flights(ds.scenarios, seed, label_fraction=label_fraction)
        parts = sp.frames(ds.flights)
        tuned = tuned_model(detector, parts.train, parts.y_train, parts.val, cfg.gps.rate_hz, 1.0, model_dir,
                            budget=budget)
        test = np.sort(np.asarray(sp.test))
    else:       # nothing to tune: every flight is a test flight
        tuned = shipped_tuned(shipped)
        test = np.sort(ds.scenarios.flight_id.to_numpy())
    t_tune = time.perf_counter() - t0
    det = tuned.detector if threshold == "f1" else tuned.detector.at_budget()
    if max_flights is not None:
        test = test[:max_flights]
    attacked = ds.scenarios.set_index("flight_id").loc[test, "attacked"].to_numpy(bool)
    P = len(policies)
    return {"cfg": cfg, "tuned": tuned, "det": det, "test": test, "t_tune": t_tune,
            "flights": np.tile(test, P), "attacked": np.tile(attacked, P),
            "pol": np.repeat(np.array(policies, dtype=object), len(test))}


def _outcome(p: dict[str, Any], r, detector: str, threshold: str, policies: tuple[str, ...],
             t_fly: float) -> tuple[dict[str, Any], pd.DataFrame, pd.DataFrame]:
    """One configuration's results, trajectories and alerts from its flown batch ``r``."""
    flights, pol, det, tuned = p["flights"], p["pol"], p["det"], p["tuned"]
    t = r["t"]
    rows_by_policy: dict[str, list[dict[str, Any]]] = {q: [] for q in policies}
    per_flight = []
    for b in range(len(flights)):
        m = flight_metrics(t, r["label"][b], r["true_pos"][b], r["est_pos"][b], r["ref_pos"][b],
                           r["admission"]["fused"][b], {"clear": r["admission"]["readmit"][b] == READMIT_CLEAR,
                                                        "stale": r["admission"]["readmit"][b] == READMIT_STALE})
        rows_by_policy[pol[b]].append(m)
        per_flight.append({"policy": pol[b], "flight_id": int(flights[b]), **m})
    results = {
        "detector": detector, "threshold": det.threshold_, "threshold_rule": threshold, "params": tuned.params,
        "val_f1": tuned.val_f1,
        "test_flights": len(p["test"]), "tune_seconds": p["t_tune"], "model_from_cache": tuned.cached,
        "fly_seconds": t_fly,
        "policies": {q: summarize_policy(rows_by_policy[q]) for q in policies},   # exclusion P/R/F1 included
        "flights": per_flight,
    }
    # per-step trajectories of every flight and policy (figures, further analysis)
    n = len(t)
    traj = pd.DataFrame({
        "policy": np.repeat(pol, n), "flight_id": np.repeat(flights, n), "t": np.tile(t, len(flights)),
        "label": r["label"].reshape(-1).astype(np.int8),
        # float32: centimetre resolution within 100 km, half the size
        **{f"{k}_{a}": r[k][..., i].reshape(-1).astype(np.float32)
           for k in ("true_pos", "est_pos", "gps_pos", "ref_pos") for i, a in enumerate("xyz")},
        **{k: r["admission"][k].reshape(-1) for k in ("fused", "std_scale", "reset", "score", "alarm")},
    })
    # alerts of the resilient flights, from their recorded residues and online scores
    alerts = pd.DataFrame()
    if "resilient" in policies:
        sel = np.nonzero(pol == "resilient")[0]
        cols = {c: r[g.name][sel][..., i].reshape(-1) for g in (*RESIDUES, GROUPS["gps_vel"]) if g.name in r
                for i, c in enumerate(g.columns)}
        X = pd.DataFrame({"flight_id": np.repeat(flights[sel], n), "t": np.tile(t, len(sel)), **cols})
        # typed by shape (first step and 5 s later), as the live monitor types its alerts
        alerts = alerts_frame(alerts_from_scores(X, r["admission"]["score"][sel].reshape(-1), det,
                                                 typer=alert_typer(X)))
        results["alerts"] = int(len(alerts))
    return results, traj, alerts


def _fly_configs(paths: list[tuple[Path, Path]], *args: Any) -> list[tuple[dict[str, Any], pd.DataFrame, pd.DataFrame]]:
    """One work unit: the configurations' datasets (and model caches) at ``paths`` flown in
    one batch under ``run_configs``."""
    return run_configs([(load_dataset(p), m) for p, m in paths], *args)


def batches_of(configs: list[SimConfig], n: int) -> list[list[int]]:
    """Indices of ``configs`` in at most about ``n`` closed-loop batches: configurations that
    can fly together (``mixable``) are dealt into ``n`` batches in order; others apart."""
    out = []
    for cl in mixable_families(configs):
        k = max(1, min(len(cl), round(n * len(cl) / len(configs))))
        out += [list(chunk) for chunk in np.array_split(np.array(cl), k)]
    return [[int(i) for i in b] for b in out]


def run_resilience(profile: str | Profile, detector: str, out: Path, cache_dir: Path, progress: bool = True,
                   workers: int | None = None, seed: int = 0, label_fraction: float = 0.2,
                   policies: tuple[str, ...] = POLICIES, admission: AdmissionConfig | None = None,
                   max_flights: int | None = None, threshold: str = "f1", backend: Backend | None = None,
                   device: str = "auto", shipped: str | None = None) -> dict[str, Any]:
    """Work units on ``backend`` (default: local processes): the datasets to simulate, the
    detector to tune per configuration (``device``: where a network trains), then one
    closed-loop batch per configuration (its test flights under every policy).
    ``shipped``: a shipped detector (of method ``detector``) drives every configuration;
    nothing is tuned and every flight of the profile's datasets is a test flight."""
    from quadformer.report.resilience import write_resilience_report

    prof = get_profile(profile).for_resilience()
    get(detector)    # unknown names fail before any work
    if threshold not in THRESHOLDS:
        raise ValueError(f"threshold: unknown choice {threshold!r}; choose from {', '.join(THRESHOLDS)}")
    check_device(device, backend, workers)   # an unavailable GPU fails before any work
    out = Path(out)
    t_start = time.perf_counter()
    paths = ensure_datasets(prof, cache_dir, progress=progress, workers=workers, backend=backend)
    t_sim = time.perf_counter() - t_start
    model_dirs = {name: model_dir_for(cache_dir, p, seed, label_fraction) for name, p in paths.items()}
    tuning = (ensure_tuned([(name, p, model_dirs[name]) for name, p in paths.items()], [detector], seed,
                           label_fraction, 1.0, device=device, progress=progress, workers=workers, backend=backend,
                           budget=prof.budget) if shipped is None else
              {(name, detector): {"cached": True, "seconds": 0.0} for name in paths})
    (out / "trajectories").mkdir(parents=True, exist_ok=True)
    names = list(paths)
    config_of = dict(profile_configs(prof))
    batches = batches_of([config_of[n] for n in names], batch_count(workers, backend))
    units = [([(paths[names[i]], model_dirs[names[i]]) for i in b], detector, seed, label_fraction, tuple(policies),
              admission, max_flights, threshold, prof.budget, shipped) for b in batches]
    flown = run_jobs(_fly_configs, units, workers=workers, progress=progress, desc="fly", unit="batch",
                     backend=backend, labels=[f"configs {', '.join(names[i] for i in b)}, seed {seed}, "
                                              f"detector {detector}" for b in batches])
    by_index = {i: out for b, outs in zip(batches, flown) for i, out in zip(b, outs)}
    outputs = [by_index[i] for i in range(len(names))]
    configs, all_alerts = [], []
    for (model, noise, attack), name, (res, traj, alerts) in zip(prof.grid, paths, outputs):
        unit = tuning[(name, detector)]
        res["model_from_cache"] = bool(unit["cached"])
        if not unit["cached"]:
            res["tune_seconds"] = unit["seconds"]
        with atomic_path(out / "trajectories" / f"{name}.parquet") as tmp:
            traj.to_parquet(tmp, index=False)
        if len(alerts):
            all_alerts.append(alerts.assign(config=name))
        configs.append({"name": name, "model": model, "noise": noise, "attack": attack,
                        "dataset": str(paths[name]), **res})
    alerts_all = pd.concat(all_alerts, ignore_index=True) if all_alerts else pd.DataFrame(
        columns=["config", *ALERT_COLUMNS])
    with atomic_path(out / "alerts.csv") as tmp:
        alerts_all.to_csv(tmp, index=False)
    results = {
        "profile": prof.name, "flights_per_config": prof.flights, "duration_s": prof.duration,
        "detector": detector, "threshold_rule": threshold, "max_test_flights": max_flights, "seed": seed,
        "label_fraction": label_fraction, "shipped": shipped,
        "training_budget": (training_budget_doc(prof.budget, [detector]) if shipped is None else
                            {"name": "shipped", "rule": f"the shipped detector {shipped}'s own (`quadformer zoo "
                             f"show {shipped}`)"}),
        "policies": list(policies),
        "admission": vars(admission or AdmissionConfig()),
        "protocol": ("detector tuned on train/validation flights as in the detection benchmark; test flights "
                     "flown again in closed loop under each policy (same missions, wind, noise and attacks)"
                     if shipped is None else
                     f"the shipped detector {shipped} (nothing tuned); flights of these datasets, new to it, flown "
                     "again in closed loop under each policy (same missions, wind, noise and attacks)"),
        "configs": configs, "versions": package_versions(),
        "provenance": provenance({"dataset": prof.seed, **({"split": seed} if shipped is None else {})}, prof.name),
        "timing_s": {"simulate_datasets": t_sim, "total": time.perf_counter() - t_start},
    }
    write_json(out / "results.json", results)
    write_resilience_report(results, out)
    return results
