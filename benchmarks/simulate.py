"""Closed-loop simulation speed: simulated flight-seconds per wall-second and peak memory.

Full loop (plant, sensors, attacks, EKF in the loop, writing Parquet), Model II in Dryden
wind, bias attacks on half the flights, one batch of each size in a fresh process.
The last line printed is one JSON object with the figures.

    python benchmarks/simulate.py [--batches 256 1024] [--duration 60]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time


def child(batch: int, duration: float) -> dict:
    from quadformer.config import AttackConfig, SimConfig
    from quadformer.dataset import write_dataset
    from quadformer.io import set_threads
    from quadformer.simulation import simulate

    set_threads()
    cfg = SimConfig(model="II", noise="laplace", flights=batch, batch_size=batch, duration=duration,
                    attack=AttackConfig(kind="bias", onset=(10.0, min(40.0, duration - 1.0))))
    t0 = time.perf_counter()
    ds = simulate(cfg)
    t1 = time.perf_counter()
    with tempfile.TemporaryDirectory() as d:
        write_dataset(ds, f"{d}/ds")
    t2 = time.perf_counter()
    return {"batch": batch, "flights": batch, "duration_s": duration, "wall_s": round(t2 - t0, 2),
            "simulate_s": round(t1 - t0, 2), "write_s": round(t2 - t1, 2),
            "flight_seconds_per_wall_second": round(batch * duration / (t2 - t0), 1),
            "peak_rss_mib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batches", type=int, nargs="+", default=[256, 1024])
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--child", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args.child, args.duration)))
        return
    results = []
    for b in args.batches:
        out = subprocess.run([sys.executable, __file__, "--child", str(b), "--duration", str(args.duration)],
                             check=True, capture_output=True, text=True).stdout.strip().splitlines()[-1]
        r = json.loads(out)
        print(f"batch {b}: {r['flight_seconds_per_wall_second']} flight-s/s, wall {r['wall_s']} s, "
              f"peak RSS {r['peak_rss_mib']} MiB", flush=True)
        results.append(r)
    import os
    import platform
    print(json.dumps({"benchmark": "simulate", "model": "II", "cpus": os.cpu_count(),
                      "machine": platform.machine(), "results": results}))


if __name__ == "__main__":
    main()
