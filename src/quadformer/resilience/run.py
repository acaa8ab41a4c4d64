"""The resilience benchmark: closed-loop flights under four GPS admission policies.

For each of the paper's eight configurations: the detector is tuned exactly as in the
detection benchmark (train/validation flights of the cached dataset), then the *test*
flights are flown again in closed loop, once per policy, in one batch: same missions,
wind, sensor noise and attacks (flight i's randomness depends only on the configuration,
its seed and i), so the policies differ only in how they fuse GPS. The naive policy
reproduces the dataset's flights.

Metrics per policy (attack steps: fixes that are spoofed):
- estimate error during attacks: RMS and max of |estimated - true position|;
- the largest deviation of the true vehicle from its mission during attacks;
- time from attack onset to the first excluded fix (detected flights);
- time from the first honest fix after the attack to re-admission (flights excluded at the
  end of the attack);
- share of clean-flight time with GPS wrongly excluded.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from quadformer.evaluation.benchmark import PROFILES, Profile, ensure_datasets, model_dir_for, tuned_model
from quadformer.evaluation.protocol import split_flights, training_labels
from quadformer.resilience.admission import POLICIES, Admission, AdmissionConfig
from quadformer.resilience.alerts import alerts_frame, alerts_from_scores
from quadformer.resilience.online import OnlineScorer
from quadformer.simulation.closed_loop import RECORDS, column_names, simulate_batch
from quadformer.simulation.dataset import load_dataset, package_versions
from quadformer.simulation.grid import PAPER_GRID

THRESHOLDS = ("f1", "budget")


def flight_metrics(t: np.ndarray, label: np.ndarray, true_pos: np.ndarray, est_pos: np.ndarray,
                   ref_pos: np.ndarray, fused: np.ndarray) -> dict[str, Any]:
    """Metrics of one flight (arrays per GPS step)."""
    err = np.linalg.norm(est_pos - true_pos, axis=1)
    dev = np.linalg.norm(true_pos - ref_pos, axis=1)
    out: dict[str, Any] = {"attacked": bool(label.any()), "max_dev_flight_m": float(dev.max())}
    if not label.any():
        out["excluded_fraction"] = float(1.0 - fused.mean())
        return out
    att = np.nonzero(label)[0]
    a0, a1 = att[0], att[-1]
    out.update(est_err_rms_m=float(np.sqrt(np.mean(err[att] ** 2))), est_err_max_m=float(err[att].max()),
               max_dev_m=float(dev[att].max()))
    excl = np.nonzero(~fused[a0:a1 + 1])[0]
    out["exclusion_delay_s"] = float(t[a0 + excl[0]] - t[a0]) if len(excl) else None
    out["excluded_at_end"] = bool(not fused[a1])
    out["readmit_delay_s"], out["readmitted"] = None, None
    if not fused[a1] and a1 + 1 < len(t):
        back = np.nonzero(fused[a1 + 1:])[0]
        out["readmitted"] = bool(len(back))
        out["readmit_delay_s"] = float(t[a1 + 1 + back[0]] - t[a1 + 1]) if len(back) else None
    after = slice(a1 + 1, min(len(t), a1 + 1 + int(round(10 / (t[1] - t[0])))))
    out["max_dev_after_m"] = float(dev[after].max()) if after.start < after.stop else None
    return out


def summarize_policy(rows: list[dict[str, Any]]) -> dict[str, Any]:
    att = [r for r in rows if r["attacked"]]
    clean = [r for r in rows if not r["attacked"]]

    def stat(key, fn, src=att):
        v = [r[key] for r in src if r.get(key) is not None and np.isfinite(r[key])]
        return float(fn(v)) if v else None

    return {
        "attacked_flights": len(att), "clean_flights": len(clean),
        "max_dev_median_m": stat("max_dev_m", np.median), "max_dev_p95_m": stat("max_dev_m", lambda v: np.percentile(v, 95)),
        "max_dev_max_m": stat("max_dev_m", np.max),
        "est_err_rms_median_m": stat("est_err_rms_m", np.median), "est_err_max_median_m": stat("est_err_max_m", np.median),
        "est_err_max_max_m": stat("est_err_max_m", np.max),
        "max_dev_after_median_m": stat("max_dev_after_m", np.median),
        "excluded_during_attack": sum(r["exclusion_delay_s"] is not None for r in att),
        "exclusion_delay_median_s": stat("exclusion_delay_s", np.median),
        "excluded_at_end": sum(bool(r["excluded_at_end"]) for r in att),
        "readmit_delay_median_s": stat("readmit_delay_s", np.median),
        "readmit_delay_max_s": stat("readmit_delay_s", np.max),
        "not_readmitted": sum(r["readmitted"] is False for r in att),
        "wrongly_excluded_fraction": stat("excluded_fraction", np.mean, clean),
        "clean_max_dev_median_m": stat("max_dev_flight_m", np.median, clean),
    }


def run_config(ds, detector: str, seed: int = 0, label_fraction: float = 0.2,
               policies: tuple[str, ...] = POLICIES, admission: AdmissionConfig | None = None,
               max_flights: int | None = None, model_dir: Path | None = None, threshold: str = "f1",
               ) -> tuple[dict[str, Any], pd.DataFrame, pd.DataFrame]:
    """Tune ``detector`` on the dataset's train/validation flights (or load it from
    ``model_dir``, the detection benchmark's cache) and fly its test flights under every
    policy. Returns (results, per-step trajectories, alerts of the resilient policy).

    threshold: the detector's alarm threshold, both chosen on validation flights: ``f1``
    maximises validation F1 (the detection benchmark's), ``budget`` allows one alarm per
    flight-hour on clean validation flights (fewer wrongful exclusions, later detections)."""
    if threshold not in THRESHOLDS:
        raise ValueError(f"threshold: unknown choice {threshold!r}; choose from {', '.join(THRESHOLDS)}")
    cfg = ds.config
    f = ds.flights
    sp = split_flights(ds.scenarios, seed, label_fraction=label_fraction)
    train = f[f.flight_id.isin(sp.train)].reset_index(drop=True)
    val = f[f.flight_id.isin(sp.val)].reset_index(drop=True)
    t0 = time.perf_counter()
    tuned = tuned_model(detector, train, training_labels(train, sp.labelled), val, cfg.gps.rate_hz, 1.0, model_dir)
    t_tune = time.perf_counter() - t0
    det = tuned.detector
    thr = tuned.threshold if threshold == "f1" else tuned.budget_threshold
    test = np.sort(np.asarray(sp.test))
    if max_flights is not None:
        test = test[:max_flights]
    attacked = ds.scenarios.set_index("flight_id").loc[test, "attacked"].to_numpy(bool)
    P = len(policies)
    flights = np.tile(test, P)
    pol = np.repeat(np.array(policies, dtype=object), len(test))
    adm = Admission(pol, cfg.gps.rate_hz, admission)
    scorer = OnlineScorer(det, len(flights), thr)
    t0 = time.perf_counter()
    r = simulate_batch(cfg, flights, np.tile(attacked, P), admission=adm, scorer=scorer)
    t_fly = time.perf_counter() - t0
    t = r["t"]
    rows_by_policy: dict[str, list[dict[str, Any]]] = {p: [] for p in policies}
    per_flight = []
    for b in range(len(flights)):
        m = flight_metrics(t, r["label"][b], r["true_pos"][b], r["est_pos"][b], r["ref_pos"][b],
                           r["admission"]["fused"][b])
        rows_by_policy[pol[b]].append(m)
        per_flight.append({"policy": pol[b], "flight_id": int(flights[b]), **m})
    results = {
        "detector": detector, "threshold": thr, "threshold_rule": threshold, "params": tuned.params,
        "val_f1": tuned.val_f1,
        "test_flights": len(test), "tune_seconds": t_tune, "model_from_cache": tuned.cached, "fly_seconds": t_fly,
        "policies": {p: summarize_policy(rows_by_policy[p]) for p in policies},
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
        cols = {c: r[k][sel][..., i].reshape(-1) for k in RECORDS if k.startswith("res_")
                for i, c in enumerate(column_names(k))}
        X = pd.DataFrame({"flight_id": np.repeat(flights[sel], n), "t": np.tile(t, len(sel)), **cols})
        alerts = alerts_frame(alerts_from_scores(X, r["admission"]["score"][sel].reshape(-1), thr, det))
        results["alerts"] = int(len(alerts))
    return results, traj, alerts


def _one(args) -> tuple[dict[str, Any], pd.DataFrame, pd.DataFrame]:
    path, detector, seed, label_fraction, policies, admission, max_flights, threads, model_dir, threshold = args
    from quadformer.simulation.dataset import set_threads
    set_threads(threads)
    return run_config(load_dataset(path), detector, seed, label_fraction, policies, admission, max_flights,
                      model_dir, threshold)


def run_resilience(profile: str | Profile, detector: str, out: Path, cache_dir: Path, progress: bool = True,
                   workers: int | None = None, seed: int = 0, label_fraction: float = 0.2,
                   policies: tuple[str, ...] = POLICIES, admission: AdmissionConfig | None = None,
                   max_flights: int | None = None, threshold: str = "f1") -> dict[str, Any]:
    from quadformer.detectors import get
    from quadformer.report.resilience import write_resilience_report

    prof = PROFILES[profile] if isinstance(profile, str) else profile
    get(detector)    # unknown names fail before any work
    if threshold not in THRESHOLDS:
        raise ValueError(f"threshold: unknown choice {threshold!r}; choose from {', '.join(THRESHOLDS)}")
    out = Path(out)
    t_start = time.perf_counter()
    paths = ensure_datasets(prof, cache_dir, progress=progress, workers=workers)
    t_sim = time.perf_counter() - t_start
    (out / "trajectories").mkdir(parents=True, exist_ok=True)
    workers = workers or min(len(paths), os.cpu_count() or 1)
    threads = max(1, (os.cpu_count() or 1) // workers)
    jobs = [(p, detector, seed, label_fraction, tuple(policies), admission, max_flights, threads,
             model_dir_for(cache_dir, p, seed, label_fraction), threshold) for p in paths.values()]
    bar = None
    if progress:
        from tqdm.auto import tqdm
        bar = tqdm(total=len(jobs), desc="fly", unit="config")
    outputs = []
    try:
        if workers == 1:
            for j in jobs:
                outputs.append(_one(j))
                if bar is not None:
                    bar.update(1)
        else:
            with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn")) as pool:
                for res in pool.map(_one, jobs):
                    outputs.append(res)
                    if bar is not None:
                        bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    configs, all_alerts = [], []
    for (model, noise, attack), name, (res, traj, alerts) in zip(PAPER_GRID, paths, outputs):
        _atomic_parquet(traj, out / "trajectories" / f"{name}.parquet")
        if len(alerts):
            all_alerts.append(alerts.assign(config=name))
        configs.append({"name": name, "model": model, "noise": noise, "attack": attack,
                        "dataset": str(paths[name]), **res})
    alerts_all = pd.concat(all_alerts, ignore_index=True) if all_alerts else pd.DataFrame(
        columns=["config", "flight_id", "start_s", "onset_s", "attack_type", "score", "end_s"])
    tmp = out / "alerts.csv.tmp"
    alerts_all.to_csv(tmp, index=False)
    tmp.replace(out / "alerts.csv")
    results = {
        "profile": prof.name, "flights_per_config": prof.flights, "duration_s": prof.duration,
        "detector": detector, "threshold_rule": threshold, "max_test_flights": max_flights, "seed": seed,
        "label_fraction": label_fraction,
        "policies": list(policies),
        "admission": vars(admission or AdmissionConfig()),
        "protocol": "detector tuned on train/validation flights as in the detection benchmark; test flights "
                    "flown again in closed loop under each policy (same missions, wind, noise and attacks)",
        "configs": configs, "versions": package_versions(),
        "timing_s": {"simulate_datasets": t_sim, "total": time.perf_counter() - t_start},
    }
    tmp = out / "results.json.tmp"
    tmp.write_text(json.dumps(results, indent=2, default=float))
    tmp.replace(out / "results.json")
    write_resilience_report(results, out)
    return results


def _atomic_parquet(df: pd.DataFrame, path: Path) -> None:
    tmp = path.with_name(path.name + ".tmp")
    df.to_parquet(tmp, index=False)
    tmp.replace(path)
