"""Log processing speed: parse + filter replay + score, in flight-seconds per wall-second.

On one thread: read a fixture log (the simulated ArduCopter log, 60 s, by default), replay the
project's filter over it (``--residues ekf``) and score the rows with a detector fitted on a
small simulated dataset of the log's sensor configuration; then the same log's streams
repeated end to end to ``--hours`` of flight, which shows how the cost grows with length.
Prints where the time goes (reading, replay, scoring); the last line is one JSON object.

    python benchmarks/logs.py [--log tests/fixtures/logs/sim_copter.bin] [--hours 0.1] [--method chi2]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

ROOT = Path(__file__).resolve().parents[1]


def repeated(log, hours: float):
    """The log's streams repeated end to end (times shifted) to about ``hours`` of flight."""
    from quadformer.logs import FlightLog

    t_all = np.concatenate([df["t"].to_numpy() for df in log.streams.values()])
    span = float(t_all.max() - t_all.min()) + 0.05
    n = max(1, int(np.ceil(hours * 3600 / span)))
    streams = {}
    for name, df in log.streams.items():
        parts = []
        for k in range(n):
            part = df.copy()
            part["t"] = part["t"] + k * span
            parts.append(part)
        streams[name] = pd.concat(parts, ignore_index=True)
    end = float(streams["imu"]["t"].iloc[-1])
    return dataclasses.replace(log, segments=[(float(streams["imu"]["t"].iloc[0]), end)], **streams), n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--log", type=Path, default=ROOT / "tests" / "fixtures" / "logs" / "sim_copter.bin")
    ap.add_argument("--hours", type=float, default=0.1, help="length of the repeated log (h)")
    ap.add_argument("--method", default="chi2")
    args = ap.parse_args()
    torch.set_num_threads(1)

    from quadformer.config import AttackConfig, SimConfig
    from quadformer.detectors import make
    from quadformer.logs import read_log
    from quadformer.logs.detect import detect_log
    from quadformer.estimator.online import FilterConfig
    from quadformer.logs.replay import ekf_rows
    from quadformer.simulation import simulate

    t0 = time.perf_counter()
    log = read_log(args.log)
    t_read = time.perf_counter() - t0
    sensors = "gps+imu+mag+baro" if log.odometry is None else "gps+imu+vio+mag+baro"
    sim = simulate(SimConfig(flights=4, duration=30.0, sensors=sensors, attack=AttackConfig(kind="bias", fraction=0.5, onset=(8.0, 15.0))))
    f = sim.flights
    det = make(args.method).fit(f, f.label.to_numpy())
    det.calibrate(float(np.percentile(det.decision_function(f), 99)))
    config = FilterConfig.matching(sim.meta["config"])

    results = []
    for name, lg in (("log", log), ("repeated", repeated(log, args.hours)[0])):
        t0 = time.perf_counter()
        rows = ekf_rows(lg, 0, config).rows
        t_replay = time.perf_counter() - t0
        t0 = time.perf_counter()
        det.decision_function(rows)
        t_score = time.perf_counter() - t0
        flight_s = float(rows.t.iloc[-1] - rows.t.iloc[0])
        wall = (t_read if name == "log" else 0.0) + t_replay + t_score
        r = {"case": name, "flight_s": round(flight_s, 1), "read_s": round(t_read, 3) if name == "log" else None,
             "replay_s": round(t_replay, 3), "score_s": round(t_score, 3),
             "flight_s_per_wall_s": round(flight_s / wall, 1),
             "seconds_per_flight_hour": round(3600 * wall / flight_s, 1),
             "imu_samples": int(len(lg.imu)), "gps_steps": int(len(rows))}
        print(f"{name}: {flight_s:.0f} flight-s in {wall:.2f} s (read {t_read if name == 'log' else 0:.2f}, "
              f"replay {t_replay:.2f}, score {t_score:.2f}): {r['flight_s_per_wall_s']}x real time, "
              f"{r['seconds_per_flight_hour']} s per flight-hour", flush=True)
        results.append(r)
    t0 = time.perf_counter()
    detect_log(args.log, det, "ekf", config)
    t_all = time.perf_counter() - t0
    print(json.dumps({"benchmark": "logs", "log": str(args.log), "sensors": sensors, "method": args.method,
                      "threads": 1, "detect_log_s": round(t_all, 3), "results": results}))


if __name__ == "__main__":
    main()
