"""The demo: its plan (the work units still to do, for one progress bar over all of them,
and an estimate of how long they take on this machine) and its run (``run_demo_profile``:
the profile's datasets, the detection benchmark, then the resilience benchmark).

The estimate counts the work (flights x steps to simulate, models to train at the demo's
training budget, datasets to score, closed-loop batches to fly) and prices it with costs
measured on a 2-core machine (``COSTS``), scaled by the cores this machine has. It is
an estimate: another load on the machine, a slower or faster core, change the real time.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from quadformer.experiments.cache import (batch_count, cached_model, dataset_key, model_dir_for, trains_network,
                                          _readable)
from quadformer.experiments.grid import Profile, dataset_summary, get_profile, profile_configs

#: cores of the machine the costs were measured on
CALIBRATION_CORES = 2

#: costs (seconds) per unit of work, measured on an idle 2-core machine (``make demo`` from a
#: fresh clone). Simulation: the per-step cost of a batch (about 4.5 ms whatever its size)
#: and the cost per flight-step on top. Tuning and scoring: one configuration of 20 flights x
#: 60 s at the demo's budget. Resilience: per step of a closed-loop batch and per flight-step
#: on top (QUADFormer scored online included).
COSTS = {
    "sim_step": 0.0045,
    "sim_flight_step": 0.0001,
    "tune_statistic": 0.2,      # chi2, cusum, sprt, bht and the reference tests (chi2-vref, cusum-vref, cusum-ref)
    "tune_windows": 2.2,        # pca, svm
    "tune_network": 3.2,        # cnn, lstm (per method)
    "tune_quadformer": 21.0,    # quadformer and its ablations (training and the alarm-rule scorings)
    "evaluate": 12.0,           # scoring one configuration's test flights with every method and typing
                                # every alarm run by shape (the demo's detectors raise many)
    "fly_step": 0.0045,
    "fly_flight_step": 0.00026,
    "overhead": 5.0,            # worker start-up, imports, reports
}


@dataclass(frozen=True)
class DemoPlan:
    units: int              # work units the progress bar counts
    estimate_s: float       # expected duration on this machine
    flights: int            # flights to simulate (datasets not cached)
    steps: int              # simulation steps per flight
    models: int             # models to tune (not cached)

    def describe(self) -> str:
        return (f"Estimated duration: about {max(1, round(self.estimate_s / 60))} min on this machine "
                f"({os.cpu_count() or 1} cores; an estimate from the work to do: {self.flights} flights x "
                f"{self.steps} steps to simulate, {self.models} models to tune at the demo's training budget, "
                f"then scoring and the resilience flights; another load on the machine makes it longer).")


def _tune_cost(method: str) -> float:
    if method.startswith("quadformer"):
        return COSTS["tune_quadformer"]
    if trains_network(method):
        return COSTS["tune_network"]
    if method in ("pca", "svm"):
        return COSTS["tune_windows"]
    return COSTS["tune_statistic"]


def plan(profile: Profile, methods: list[str], cache_dir: Path, workers: int | None = None,
         seed: int = 0, label_fraction: float = 0.2, resilience: bool = True) -> DemoPlan:
    """The work units of a demo run over ``profile`` and their expected duration."""
    from quadformer.experiments.resilience import batches_of
    from quadformer.simulation.simulate import plan_batches

    cores = os.cpu_count() or 1
    n_workers = batch_count(workers)
    configs = profile_configs(profile)
    missing = [cfg for name, cfg in configs if not _readable(Path(cache_dir) / f"{name}-{dataset_key(cfg)}")]
    batches = plan_batches(missing, n_workers) if missing else []
    steps = configs[0][1].n_steps if configs else 0
    sim_s = 0.0
    if batches:
        biggest = max(sum(len(ids) for _, ids in b) for b in batches)
        rounds = math.ceil(len(batches) / n_workers)
        sim_s = rounds * steps * (COSTS["sim_step"] + COSTS["sim_flight_step"] * biggest)
    size = profile.flights * profile.duration / (20 * 60.0)     # the costs are per 20 flights of 60 s
    tune_units, tune_s = 0, 0.0
    for name, cfg in configs:
        model_dir = model_dir_for(cache_dir, Path(cache_dir) / f"{name}-{dataset_key(cfg)}", seed, label_fraction)
        for m in methods:
            if cached_model(m, 1.0, model_dir, profile.budget) is None:
                tune_units += 1
                tune_s += _tune_cost(m) * size
    tune_s /= n_workers
    eval_s = COSTS["evaluate"] * size * len(configs) * CALIBRATION_CORES / max(cores, 1)
    fly_s, fly_units = 0.0, 0
    if resilience:     # the test flights (a fifth) under four policies, in batches mixing configurations
        fly_cfgs = [cfg for _, cfg in profile_configs(profile.for_resilience())]
        fly = batches_of(fly_cfgs, n_workers)
        fly_units = len(fly)
        per_config = 4 * max(1, round(0.2 * profile.flights))
        biggest = max(len(b) for b in fly) * per_config
        fly_s = math.ceil(len(fly) / n_workers) * steps * (COSTS["fly_step"] + COSTS["fly_flight_step"] * biggest)
    units = len(batches) + tune_units + len(configs) + fly_units
    total = COSTS["overhead"] + sim_s + tune_s + eval_s + fly_s
    return DemoPlan(units, total, sum(c.flights for c in missing), steps, tune_units)


@dataclass
class DemoRun:
    datasets: list[dict[str, Any]]     # per configuration: its name and ``grid.dataset_summary``
    detection: dict[str, Any]          # the detection benchmark's results (``detection.run_benchmark``)
    resilience: dict[str, Any]         # the resilience benchmark's results (``resilience.run_resilience``)
    phases: dict[str, float]           # s: simulate, detection, resilience


def run_demo_profile(out: Path, cache_dir: Path, methods: list[str], profile: str | Profile = "demo",
                     detector: str = "quadformer", progress: bool = True, todo: DemoPlan | None = None,
                     workers: int | None = None) -> DemoRun:
    """A profile end to end: its datasets (simulated, or from the cache), the detection
    benchmark of ``methods`` into ``out/detection``, then the resilience benchmark driven by
    ``detector`` into ``out/resilience``; one progress bar over the plan's units (``todo``,
    planned here when not given)."""
    from quadformer.dataset import load_dataset
    from quadformer.experiments.cache import ensure_datasets
    from quadformer.experiments.detection import run_benchmark
    from quadformer.experiments.pool import SharedBar
    from quadformer.experiments.resilience import run_resilience

    prof = get_profile(profile)
    bar = None
    if progress:
        todo = todo or plan(prof, methods, cache_dir, workers, resilience=True)
        bar = SharedBar(todo.units, desc="demo")
    prog = bar if bar is not None else False
    phases = {}
    try:
        t0 = time.perf_counter()
        paths = ensure_datasets(prof, cache_dir, progress=prog, workers=workers)
        phases["simulate"] = time.perf_counter() - t0
        rows = [{"config": name, **dataset_summary(load_dataset(p))} for name, p in paths.items()]
        t0 = time.perf_counter()
        detection = run_benchmark(prof, methods, Path(out) / "detection", cache_dir, progress=prog, workers=workers)
        phases["detection"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        resilience = run_resilience(prof, detector, Path(out) / "resilience", cache_dir, progress=prog,
                                    workers=workers)
        phases["resilience"] = time.perf_counter() - t0
    finally:
        if bar is not None:
            bar.close()
    return DemoRun(rows, detection, resilience, phases)


# -- the demo on the shipped detectors (``quadformer demo``; ``--train`` is the one above) --------
#: the demo's test flights: the paper's eight configurations, 20 new flights each (seed
#: DEMO_SEED: neither the zoo's nor a benchmark's), every one a test flight; the resilience run
#: flies four configurations' first SHIPPED_FLY flights again under every policy
SHIPPED_FLY = 4
#: the flights written as autopilot logs for ``detect``: GPS, IMU, magnetometer and barometer
#: with the fleet's noise, one of the two spoofed
LOG_FLIGHTS = 2
LOG_DURATION = 40.0     # s


def versus_paper(detection: dict[str, Any], method: str = "quadformer") -> list[dict[str, Any]]:
    """Per configuration of a demo run: ``method``'s test F1, its 95% bootstrap interval, the paper
    profile's F1 (``zoo.PAPER_PROFILE_F1``) and whether the interval holds it."""
    from quadformer.experiments.zoo import PAPER_PROFILE_F1

    out = []
    for c in detection["configs"]:
        m = c["methods"].get(method)
        paper = PAPER_PROFILE_F1.get(method, {}).get(c["name"])
        if m is None or paper is None:
            continue
        ci = m.get("f1_ci95")
        out.append({"config": c["name"], "f1": m["f1"], "ci95": ci, "paper": paper,
                    "holds": bool(ci is not None and ci[0] <= paper <= ci[1])})
    return out


def shipped_profile() -> Profile:
    from quadformer.experiments.grid import DEMO_RESILIENCE_GRID
    from quadformer.experiments.zoo import DEMO_SEED

    return Profile("demo", 20, seed=DEMO_SEED, stress_flights=0, resilience_grid=DEMO_RESILIENCE_GRID)


@dataclass
class ShippedDemo:
    datasets: list[dict[str, Any]]
    detection: dict[str, Any]
    resilience: dict[str, Any]
    logs: Any                          # report.detection_outputs.LogsDetection
    log_detector: str                  # the shipped detector the logs were scored with
    shipped: dict[str, str]            # method -> shipped detector of the comparison
    phases: dict[str, float]


def run_shipped_demo(out: Path, cache_dir: Path, progress: bool = True, workers: int | None = None,
                     profile: Profile | None = None, fly: int = SHIPPED_FLY,
                     log_duration: float = LOG_DURATION) -> ShippedDemo:
    """The shipped detectors on new flights: the paper's eight configurations scored by the
    ``vio`` set's detectors (nothing tuned), QUADFormer's shipped detector driving the resilient
    estimator on four of them (their first ``fly`` flights), and ``detect`` on simulated flights
    (``log_duration`` s) written as a PX4 ULog and an ArduPilot DataFlash log, with the shipped
    detector ``detect`` picks for them. ``profile``: another set of test flights (its seed not
    the zoo's)."""
    from quadformer.dataset import load_dataset
    from quadformer.detectors import pretrained
    from quadformer.experiments.cache import ensure_configs
    from quadformer.experiments.detection import run_shipped
    from quadformer.experiments.resilience import run_resilience

    prof = profile or shipped_profile()
    shipped = {e.method: e.name for e in pretrained.entries().values() if e.set.name == "vio"}
    if not shipped:
        raise ValueError("no shipped detector of the vio set: build them with `quadformer zoo build`")
    phases: dict[str, float] = {}
    t0 = time.perf_counter()
    paths = ensure_configs(profile_configs(prof), cache_dir, progress=progress, workers=workers)
    rows = [{"config": name, **dataset_summary(load_dataset(p))} for name, p in paths.items()]
    phases["simulate"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    detection = run_shipped(prof, shipped, Path(out) / "detection", cache_dir, progress=progress, workers=workers)
    phases["detection"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    resilience = run_resilience(prof, "quadformer", Path(out) / "resilience", cache_dir, progress=progress,
                                workers=workers, max_flights=fly, shipped=shipped["quadformer"])
    phases["resilience"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    logs, name = _detect_on_logs(Path(out), cache_dir, log_duration, workers)
    phases["logs"] = time.perf_counter() - t0
    return ShippedDemo(rows, detection, resilience, logs, name, shipped, phases)


#: the demo's vehicle without a camera flying a consistent drift: a receiver of the u-blox class
#: (velocity noise 0.1 m/s, position 0.3 m white over 0.5 m of slow error), the fleet's IMU
DRIFT_RECEIVER = {"gps": {"vel_std": 0.1, "pos_std_h": 0.3, "gm_std": 0.5}}
#: m/s, switched on at once: the position and the velocity agree (glr, at the threshold real clean
#: flights need, sees such a drift from about 2 m/s on; docs/field.md)
DRIFT_RATE = 3.0


def _detect_on_logs(out: Path, cache_dir: Path, duration: float, workers: int | None = None):
    """Simulated flights written as autopilot logs (kept in the cache), scored by ``detect``'s
    route with the shipped detector it picks for them: two flights with the fleet's noise (one
    under a bias), and a vehicle without a camera under a consistent drift switched on at once
    (``drift_0000``); the onsets come after the shipped ``glr`` has calibrated itself on the
    flight's first 20 s in the air (before, it sees only what a vehicle 10 times noisier would let
    it see)."""
    from quadformer.config import SimConfig, merge
    from quadformer.experiments.cache import dataset_key
    from quadformer.experiments.flight_logs import simulate_with_logs
    from quadformer.experiments.zoo import DEMO_SEED, FLEET_NOISE
    from quadformer.logs import find_logs, read_log
    from quadformer.logs.detect import shipped_for
    from quadformer.report.detection_outputs import detect_logs

    cfg = SimConfig.from_dict(merge(FLEET_NOISE, {
        "model": "I", "noise": "gaussian", "sensors": "gps+imu+mag+baro", "flights": LOG_FLIGHTS, "duration": duration,
        "seed": DEMO_SEED, "attack": {"kind": "bias", "fraction": 0.5, "magnitude": [4.0, 8.0],
                                      "onset": [0.7 * duration, 0.8 * duration]}}))
    drift = SimConfig.from_dict(merge(merge(FLEET_NOISE, DRIFT_RECEIVER), {
        "model": "I", "noise": "gaussian", "sensors": "gps+imu+mag+baro", "flights": 1, "duration": duration,
        "seed": DEMO_SEED + 1, "attack": {"kind": "drift", "fraction": 1.0, "rate": [DRIFT_RATE, DRIFT_RATE],
                                          "onset": [0.75 * duration, 0.75 * duration], "onset_step": True,
                                          "axes": "xy"}}))
    paths = []
    for c, name in ((cfg, "flight"), (drift, "drift")):      # their own names beside each other's
        where = Path(cache_dir) / f"demo-logs-{name}-{dataset_key(c)}"
        if not (where / "logs").is_dir():
            simulate_with_logs(c, where, ("ulog", "dataflash"), overwrite=True, name=name)
        paths += find_logs([where / "logs"])
    det, config = shipped_for(read_log(paths[0]))
    run = detect_logs(paths, det, out / "logs", "ekf", config, model=f"shipped:{det.zoo_name_}",
                      workers=min(len(paths), workers or os.cpu_count() or 1))
    return run, det.zoo_name_
