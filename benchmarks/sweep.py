"""The benchmark's work units on the local process pool and on Ray, on this machine.

Runs ``run_benchmark`` twice from an empty cache, once per backend, on the same CPUs
(``--cpus`` local workers; a Ray runtime started here with as many CPUs), and prints: the
wall time of each, Ray's overhead in %, the number of work units (datasets simulated,
detectors tuned) and their median duration (measured in the workers), whether both runs gave
the same figures, and the projected wall time of the paper profile (600 flights per
configuration) times ``--proj-seeds`` seeds on ``--proj-cores`` cores.

The projection scales the measured units to the paper's flights per configuration: a dataset
unit with the simulator's cost per step, ``a + b * batch`` (calibrated here on two short
batches, 1 and 64 flights, one thread; the paper's 600 flights are batches of 256, 256 and
88), times the ratio of the measured unit to that model at the measured size; a tuning unit
and the driver's scoring of test flights linearly in flight-seconds (an upper bound: network training
is capped at a fixed number of steps per epoch). One unit per core,
the seeds one after another (as ``benchmark --seeds`` runs them), each phase (simulate, tune)
as long as its units spread longest first over the cores, and Ray's measured overhead on top.
The last line printed is one JSON object with the figures.

    python benchmarks/sweep.py                                  # the quick profile
    python benchmarks/sweep.py --flights 12 --duration 45 --configs 4 --methods chi2,cusum,svm,cnn
"""

from __future__ import annotations

import argparse
import dataclasses
import heapq
import json
import logging
import os
import statistics
import tempfile
import time
from pathlib import Path


class UnitTimes(logging.Handler):
    """Collects the unit durations ``experiments.pool`` logs."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.units: list[tuple[str, str, float]] = []

    def emit(self, record: logging.LogRecord) -> None:
        if hasattr(record, "unit_seconds"):
            self.units.append((record.unit_desc, record.unit_label, record.unit_seconds))


def spread(durations: list[float], cores: int) -> float:
    """Wall time of independent units spread longest first over ``cores`` (one unit per core)."""
    load = [0.0] * min(cores, max(1, len(durations)))
    for d in sorted(durations, reverse=True):
        heapq.heappush(load, heapq.heappop(load) + d)
    return max(load) if durations else 0.0


def stable(obj):
    """results.json without what changes from run to run (timings, paths, versions)."""
    if isinstance(obj, dict):
        return {k: stable(v) for k, v in obj.items()
                if k not in {"tune_seconds", "score_seconds", "timing_s", "versions", "dataset"}}
    if isinstance(obj, list):
        return [stable(v) for v in obj]
    return obj


def step_cost(duration: float = 5.0, batches: tuple[int, int] = (1, 64)) -> tuple[float, float]:
    """(a, b) of the simulator's wall time per 100 Hz step, ``a + b * batch`` seconds, on one thread."""
    from quadformer.config import AttackConfig, SimConfig
    from quadformer.io import set_threads
    from quadformer.simulation import simulate

    set_threads(1)
    times = []
    for b in batches:
        cfg = SimConfig(model="II", noise="laplace", flights=b, batch_size=b, duration=duration,
                        attack=AttackConfig(kind="bias", onset=(1.0, 2.0), duration=(1.0, 2.0)))
        t0 = time.perf_counter()
        simulate(cfg)
        times.append((time.perf_counter() - t0) / (duration * 100))
    b_ = (times[1] - times[0]) / (batches[1] - batches[0])
    return times[0] - b_ * batches[0], max(b_, 0.0)


def batch_sizes(flights: int, batch: int = 256) -> list[int]:
    return [min(batch, flights - s) for s in range(0, flights, batch)]


def main() -> None:
    from quadformer.experiments.detection import run_benchmark
    from quadformer.experiments.grid import get_profile
    from quadformer.experiments.pool import Backend, connect
    from quadformer.io import set_threads

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profile", default="quick")
    ap.add_argument("--flights", type=int, help="flights per configuration (default: the profile's)")
    ap.add_argument("--duration", type=float, help="seconds per flight (default: the profile's)")
    ap.add_argument("--configs", type=int, help="only the first N configurations of the profile")
    ap.add_argument("--methods", default="chi2,cusum,sprt,bht,pca,svm,cnn,lstm,quadformer")
    ap.add_argument("--cpus", type=int, default=os.cpu_count() or 1, help="local workers and Ray CPUs")
    ap.add_argument("--proj-flights", type=int, default=600, help="flights per configuration of the projection")
    ap.add_argument("--proj-seeds", type=int, default=5)
    ap.add_argument("--proj-cores", type=int, default=64)
    args = ap.parse_args()

    prof = get_profile(args.profile)
    prof = dataclasses.replace(prof, flights=args.flights or prof.flights, duration=args.duration or prof.duration,
                               grid=prof.grid[: args.configs] if args.configs else prof.grid)
    methods = [m for m in args.methods.split(",") if m]
    handler = UnitTimes()
    logger = logging.getLogger("quadformer.experiments.pool")
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG)
    set_threads()

    runs = {}
    t0 = time.perf_counter()
    connect(Backend("ray"), workers=args.cpus)           # Ray's start-up, timed apart
    ray_start = time.perf_counter() - t0
    print(f"profile {prof.name}: {len(prof.grid)} configurations x {prof.flights} flights of {prof.duration:g} s, "
          f"methods {','.join(methods)}, {args.cpus} CPUs (Ray started in {ray_start:.1f} s)", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        for kind in ("local", "ray"):
            handler.units.clear()
            t0 = time.perf_counter()
            res = run_benchmark(prof, methods, Path(tmp) / f"out-{kind}", Path(tmp) / f"cache-{kind}", progress=False,
                                workers=args.cpus, backend=Backend(kind), device="cpu")
            wall = time.perf_counter() - t0
            units = list(handler.units)
            runs[kind] = {"wall_s": wall, "units": units, "timing": res["timing_s"],
                          "figures": stable(json.loads((Path(tmp) / f"out-{kind}" / "results.json").read_text()))}
            sim = [s for d, _, s in units if d == "simulate"]
            tune = [s for d, _, s in units if d == "tune"]
            print(f"{kind:5s}: wall {wall:7.1f} s  ({len(units)} units: {len(sim)} simulate, median "
                  f"{statistics.median(sim):.1f} s; {len(tune)} tune, median {statistics.median(tune):.1f} s; "
                  f"scoring in the driver {wall - res['timing_s']['simulate'] - res['timing_s']['tune']:.1f} s)",
                  flush=True)

    local, ray = runs["local"], runs["ray"]
    overhead = 100.0 * (ray["wall_s"] - local["wall_s"]) / local["wall_s"]
    same = local["figures"] == ray["figures"]
    all_units = [s for _, _, s in local["units"]]
    print(f"Ray overhead: {overhead:+.1f}% of the local wall time ({ray['wall_s'] - local['wall_s']:+.1f} s; "
          f"start-up {ray_start:.1f} s not counted)")
    print(f"work units: {len(all_units)} per backend, median duration {statistics.median(all_units):.1f} s (local)")
    print(f"same figures in results.json: {'yes' if same else 'NO'}")

    # projection: the paper profile's flights, every configuration, seeds one after another
    a, b = step_cost()
    full = get_profile(args.profile)
    model = lambda flights, duration: duration * 100 * sum(a + b * n for n in batch_sizes(flights))  # noqa: E731
    sim_scale = model(args.proj_flights, full.duration) / model(prof.flights, prof.duration)
    print(f"simulator cost per step (one thread): {1e3 * a:.2f} ms + {1e3 * b:.3f} ms per flight of the batch")
    scale = args.proj_flights * full.duration / (prof.flights * prof.duration)
    n_cfg = len(full.grid) / len(prof.grid)
    sim = [s * sim_scale for d, _, s in local["units"] if d == "simulate"] * round(n_cfg)
    tune = [s * scale for d, _, s in local["units"] if d == "tune"] * round(n_cfg)
    drive = (local["wall_s"] - local["timing"]["simulate"] - local["timing"]["tune"]) * scale * n_cfg
    per_seed = spread(sim, args.proj_cores) + spread(tune, args.proj_cores) + drive
    projected = args.proj_seeds * per_seed * (1 + max(overhead, 0.0) / 100)
    print(f"projected: paper profile ({args.proj_flights} flights per configuration) x {args.proj_seeds} seeds on "
          f"{args.proj_cores} cores with Ray: {projected / 60:.0f} min ({per_seed / 60:.1f} min per seed: "
          f"{len(sim)} simulate units, {len(tune)} tune units, scoring {drive / 60:.1f} min in the driver)")
    print(json.dumps({
        "profile": prof.name, "configs": len(prof.grid), "flights": prof.flights, "duration_s": prof.duration,
        "methods": methods, "cpus": args.cpus, "ray_start_s": round(ray_start, 2),
        "wall_s": {k: round(v["wall_s"], 2) for k, v in runs.items()}, "ray_overhead_pct": round(overhead, 1),
        "units": len(all_units), "unit_median_s": round(statistics.median(all_units), 2), "same_figures": same,
        "step_cost_ms": [round(1e3 * a, 3), round(1e3 * b, 4)], "projected_paper_s": round(projected, 1), "projected_cores": args.proj_cores,
        "projected_seeds": args.proj_seeds}))


if __name__ == "__main__":
    main()
