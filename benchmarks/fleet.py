"""Fleet log replay: ``quadformer detect`` over a folder of real flight logs, in flight time per
wall time, on one core and on all of them.

The whole path a user runs (read each log, replay the project's filter over its raw sensors,
residues, score with a detector, alerts, report folder), through ``detect_logs`` as the CLI
calls it: once with one worker in this process, once with a worker per core. The detector:
``--model`` (a file written by ``quadformer fit``/``benchmark``), else ``--method`` fitted on a
few simulated flights of the logs' sensor set (its numbers do not matter here, its cost does).
Before timing, one small log is replayed so that the compiled filter's cache is loaded (its
first build, on a fresh install, is reported apart as ``warmup_s``). Also measured: the reading
alone (every log read once, one core). Flight time: each scored log's duration. The last line
printed is one JSON object.

    python benchmarks/fleet.py [--logs ../shared/data/real-flights] [--model FILE | --method chi2]
                               [--workers 0]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data" / "real-flights"
SMALL_LOG = ROOT / "tests" / "fixtures" / "logs" / "sample_log_small.ulg"


def detector(model: Path | None, method: str):
    from quadformer.detectors.onnx_runtime import load_model

    if model is not None:
        return load_model(model)
    from quadformer.config import AttackConfig, SimConfig
    from quadformer.detectors import make
    from quadformer.simulation import simulate

    sim = simulate(SimConfig(flights=4, duration=30.0, sensors="gps+imu+mag+baro", seed=11,
                             attack=AttackConfig(kind="bias", fraction=0.5, onset=(8.0, 15.0))))
    f = sim.flights
    det = make(method).fit(f, f.label.to_numpy())
    det.calibrate(float(np.percentile(det.decision_function(f), 99)))
    return det


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", type=Path, default=SHARED, help="folder of flight logs")
    ap.add_argument("--model", type=Path, default=None)
    ap.add_argument("--method", default="chi2")
    ap.add_argument("--workers", type=int, default=0, help="workers of the all-core run (0: one per core)")
    args = ap.parse_args()
    if not args.logs.is_dir():
        raise SystemExit(f"{args.logs}: no such folder (give --logs a folder of flight logs)")

    from quadformer.cli.common import log_paths
    from quadformer.estimator.filter_config import FilterConfig
    from quadformer.logs import read_log
    from quadformer.report.detection_outputs import detect_logs

    paths = log_paths([args.logs], None)
    det = detector(args.model, args.method)
    t0 = time.perf_counter()
    detect_logs([SMALL_LOG], det, tempfile.mkdtemp(prefix="fleet-warmup-"), "ekf", FilterConfig())
    warmup = time.perf_counter() - t0
    t0 = time.perf_counter()
    for p in paths:
        try:
            read_log(p)
        except Exception:       # noqa: BLE001  (a log the readers refuse is refused in the runs too)
            pass
    read_s = time.perf_counter() - t0
    cores = args.workers or os.cpu_count() or 1
    runs = {}
    for label, workers in (("one_core", 1), ("all_cores", cores)):
        with tempfile.TemporaryDirectory(prefix=f"fleet-{label}-") as out:
            t0 = time.perf_counter()
            run = detect_logs(paths, det, out, "ekf", FilterConfig(), workers=workers)
            wall = time.perf_counter() - t0
        scored = run.of("scored")
        flight_s = sum(o.detection.log.duration for o in scored)
        runs[label] = {"workers": workers, "wall_s": round(wall, 2), "scored": len(scored),
                       "flight_h": round(flight_s / 3600, 3), "realtime_factor": round(flight_s / wall, 1)}
        print(f"{label} ({workers} worker(s)): {len(paths)} logs, {len(scored)} scored, {flight_s / 3600:.2f} "
              f"flight-h in {wall:.1f} s: {flight_s / wall:.0f}x real time", flush=True)
    print(f"reading alone: {read_s:.1f} s; warm-up (compiled filter loaded or built): {warmup:.1f} s")
    print(json.dumps({"benchmark": "fleet", "logs": str(args.logs), "n_logs": len(paths), "detector": det.name,
                      "cores": os.cpu_count(), "read_s": round(read_s, 2), "warmup_s": round(warmup, 2), **runs}))


if __name__ == "__main__":
    main()
