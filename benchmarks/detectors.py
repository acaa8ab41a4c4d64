"""Detector speed: offline scoring throughput and online per-step latency.

For each method: fit on the training flights of a simulated dataset (Model II, laplace,
bias), then
- offline: GPS steps scored per second by ``decision_function`` on all flights (and the
  seconds to score one flight-hour, 36,000 steps);
- online: latency of one ``stream(1).update(...)`` call per GPS step, p50 and p99, one
  thread, after a few untimed steps: wall time, and the thread's CPU time (which leaves out
  waits for a core that other processes hold).
Network detectors run under each ``--runtime``: ``torch`` (the detector itself) and ``onnx``
(its exported graph scored by onnxruntime, ``detectors.export``), side by side; the other
detectors have one implementation (reported as ``torch``); QUADFormer's stream is the
step-wise one in both (``detectors.neural.quadformer_steps``: the window's step embeddings as
its state, the exported streaming graph with onnxruntime). The last line printed is one JSON
object, with the machine's load averages (1, 5, 15 min) before and after: the timings of a
shared machine say little without them.

    python benchmarks/detectors.py [--methods chi2,cusum,sprt,bht,quadformer] [--flights 40]
                                   [--runtime torch,onnx]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

WARMUP = 20    # untimed stream steps before timing (first-call allocations)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--methods", default=None)
    ap.add_argument("--flights", type=int, default=40)
    ap.add_argument("--data", type=Path, default=None, help="existing dataset directory (else simulated)")
    ap.add_argument("--runtime", default="torch,onnx",
                    help="runtimes of the network detectors, comma-separated: torch, onnx")
    args = ap.parse_args()
    torch.set_num_threads(1)
    load_before = [round(v, 2) for v in os.getloadavg()]

    from quadformer import load_dataset, simulate
    from quadformer.config import AttackConfig, SimConfig
    from quadformer.detectors import available, export_onnx, load_model, make
    from quadformer.detectors.export import RUNTIMES, exportable

    runtimes = args.runtime.split(",")
    unknown = [r for r in runtimes if r not in RUNTIMES]
    if unknown:
        ap.error(f"unknown runtime {unknown[0]!r}; choose from {', '.join(RUNTIMES)}")
    if args.data:
        ds = load_dataset(args.data)
    else:
        ds = simulate(SimConfig(model="II", noise="laplace", flights=args.flights, batch_size=args.flights,
                                attack=AttackConfig(kind="bias")))
    f = ds.flights
    ids = np.sort(f.flight_id.unique())
    train = f[f.flight_id.isin(ids[: len(ids) // 2])].reset_index(drop=True)
    flight = f[f.flight_id == ids[-1]]
    methods = available() if args.methods is None else args.methods.split(",")
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for m in methods:
            t_fit = time.perf_counter()
            det = make(m).fit(train, train.label.to_numpy())
            t_fit = time.perf_counter() - t_fit
            for runtime in runtimes:
                if runtime == "onnx" and not exportable(det):
                    continue          # not a network: one implementation, timed as torch
                scorer = det if runtime == "torch" else load_model(export_onnx(det, Path(tmp) / f"{m}.onnx"),
                                                                   runtime, threads=1)
                r = {"method": m, "runtime": runtime, "fit_s": round(t_fit, 2), **_time(scorer, f, flight)}
                print(f"{m} [{runtime}]: {r['offline_steps_per_s']} steps/s offline "
                      f"({r['seconds_per_flight_hour']} s per flight-hour), online p50 {r['online_p50_us']} us, "
                      f"p99 {r['online_p99_us']} us (CPU time p50 {r['online_cpu_p50_us']} us, "
                      f"p99 {r['online_cpu_p99_us']} us)", flush=True)
                out.append(r)
    print(json.dumps({"benchmark": "detectors", "steps": len(f), "results": out,
                      "load_avg": {"before": load_before, "after": [round(v, 2) for v in os.getloadavg()]}}))


def _time(det, f, flight) -> dict:
    """Offline throughput (best of 3) and one-flight online latency of a scorer."""
    reps = []
    for _ in range(3):
        getattr(det, "clear_cache", lambda: None)()     # time the computation, not a cache
        t0 = time.perf_counter()
        det.decision_function(f)
        reps.append(time.perf_counter() - t0)
    steps_per_s = len(f) / min(reps)
    values = flight[det.features_].to_numpy()
    warm = det.stream(1)
    for v in values[:WARMUP]:
        warm.update(v)
    lat, cpu = [], []
    stream = det.stream(1)
    for v in np.concatenate([values] * 3):
        c0, t0 = time.thread_time_ns(), time.perf_counter_ns()
        stream.update(v)
        lat.append(time.perf_counter_ns() - t0)
        cpu.append(time.thread_time_ns() - c0)
    lat_us, cpu_us = np.array(lat) / 1e3, np.array(cpu) / 1e3
    return {"offline_steps_per_s": round(steps_per_s), "seconds_per_flight_hour": round(36000 / steps_per_s, 3),
            "online_p50_us": round(float(np.percentile(lat_us, 50)), 2),
            "online_p99_us": round(float(np.percentile(lat_us, 99)), 2),
            # the thread's CPU time per step: the wall time less any time the process waited
            # for a core (on a shared machine the wall p99 mostly measures the other jobs)
            "online_cpu_p50_us": round(float(np.percentile(cpu_us, 50)), 2),
            "online_cpu_p99_us": round(float(np.percentile(cpu_us, 99)), 2)}


if __name__ == "__main__":
    main()
