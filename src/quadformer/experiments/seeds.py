"""The detection benchmark over several seeds (``benchmark --seeds`` / ``--seed-list``): the whole
protocol once per seed, each seed its own datasets and split, and the spread of every metric."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np

from quadformer.detectors import get
from quadformer.experiments.detection import run_benchmark
from quadformer.experiments.grid import Profile, get_profile
from quadformer.experiments.pool import Backend
from quadformer.experiments.provenance import provenance
from quadformer.io import package_versions, write_json

__all__ = ["SEED_METRICS", "run_seeds", "seed_summary"]


#: metrics summarised over seeds (mean, std, min, max) per configuration and method
SEED_METRICS = ("f1", "precision", "recall", "event_f1", "event_recall", "delay_median_s", "false_alarms_per_hour",
                "auroc", "auprc", "vus_pr")


def run_seeds(profile: str | Profile, methods: list[str], out: Path, cache_dir: Path, seeds: list[int],
              progress: bool = True, workers: int | None = None, label_fraction: float = 0.2,
              budget_per_hour: float = 1.0, stress: bool = False, backend: Backend | None = None,
              device: str = "auto") -> dict[str, Any]:
    """The whole protocol once per seed: seed s simulates its own datasets (the profile's
    dataset seed set to s, from which each configuration derives its own) and splits them
    with split seed s. Each run writes its own directory ``out/seed-<s>/`` (results.json,
    tables, report); ``out/results.json`` keeps every run's metrics per configuration and
    method and their mean, standard deviation (ddof 1) and min-max over the seeds, and
    ``out/report.html`` shows them."""
    from quadformer.report.detection_seeds import write_seeds_report

    prof = get_profile(profile)
    seeds = [int(s) for s in seeds]
    if not seeds or len(set(seeds)) != len(seeds) or min(seeds) < 0:
        raise ValueError(f"seeds: distinct non-negative integers needed, got {seeds}")
    for m in methods:
        get(m)
    out = Path(out)
    t_start = time.perf_counter()
    runs_: list[dict[str, Any]] = []
    for s in seeds:
        res = run_benchmark(dataclasses.replace(prof, seed=s), methods, out / f"seed-{s}", cache_dir,
                            progress=progress, workers=workers, seed=s, label_fraction=label_fraction,
                            budget_per_hour=budget_per_hour, stress=stress, backend=backend, device=device)
        runs_.append(res)
    results = {
        "profile": prof.name, "flights_per_config": prof.flights, "duration_s": prof.duration, "seeds": seeds,
        "label_fraction": label_fraction, "methods_run": methods,
        "protocol": "per seed s: datasets simulated from profile seed s (each configuration its own derived "
                    "seed), split by flight with seed s, hyper-parameters and thresholds on validation flights, "
                    "test scored once; the spread over seeds covers datasets, splits and training",
        "runs": [{"seed": s, "dir": str(out / f"seed-{s}")} for s in seeds],
        "per_seed": {str(s): {c["name"]: {m: {k: r.get(k) for k in (*SEED_METRICS, "f1_ci95")}
                                          for m, r in c["methods"].items()}
                              for c in res["configs"]} for s, res in zip(seeds, runs_)},
        "summary": seed_summary(runs_),
        "versions": package_versions(),
        "provenance": provenance({"runs": seeds}, prof.name),
        "timing_s": {"total": time.perf_counter() - t_start,
                     "per_seed": {str(s): r["timing_s"]["total"] for s, r in zip(seeds, runs_)}},
    }
    write_json(out / "results.json", results)
    write_seeds_report(results, out)
    return results


def seed_summary(runs_: list[dict[str, Any]], metrics: tuple[str, ...] = SEED_METRICS) -> dict[str, Any]:
    """Per configuration, method and metric over the runs (one per seed): mean, standard
    deviation (ddof 1; None for a single run), min, max and the number of runs with a value."""
    values: dict[str, dict[str, dict[str, list[float]]]] = {}
    for res in runs_:
        for c in res["configs"]:
            for m, r in c["methods"].items():
                for k in metrics:
                    v = r.get(k)
                    if v is not None and np.isfinite(v):
                        values.setdefault(c["name"], {}).setdefault(m, {}).setdefault(k, []).append(float(v))
    out: dict[str, Any] = {}
    for name, per_method in values.items():
        for m, per_metric in per_method.items():
            out.setdefault(name, {})[m] = {k: {
                "mean": float(np.mean(v)), "std": float(np.std(v, ddof=1)) if len(v) > 1 else None,
                "min": float(np.min(v)), "max": float(np.max(v)), "n": len(v)} for k, v in per_metric.items()}
    return out
