"""Sim-to-real: detectors trained in simulation only, evaluated on real flight logs with
injected spoofs, beside the same detectors trained on the injected logs themselves.

1. The fleet's sensor noise is estimated from the clean logs (``logs.noise``).
2. For each attack (bias 1.5-6 m, ramp 0.2-1 m/s): a simulated dataset of the logs' sensor
   configuration (GPS, IMU, magnetometer, barometer; no camera) with that noise; every method
   tuned on it under the benchmark's protocol (split by flight, threshold on validation).
3. The logs replayed with the simulation's filter tuning, each segment ``--repeat`` times with
   the attack injected into half of the replays (seeded), and scored by the simulation-trained
   detectors: event recall, median delay, point-wise F1; false alarms per flight-hour on the
   clean logs themselves (no injection).
4. The same methods trained and tested on the injected logs (``benchmark --data``'s protocol;
   the replays of one log segment stay in one part of the split; every label of the training
   recordings is used, as a fifth of one or two recordings would be none).

Prints one table per attack; the last line is one JSON object. Minutes on two cores.

    python benchmarks/sim_to_real.py [--flights 60] [--repeat 20] [--methods chi2,cusum,bht,cnn,lstm,quadformer]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
FIX = ROOT / "tests" / "fixtures" / "logs"
#: the project's shared data beside the repository (read here, never copied into it): an ArduCopter
#: SITL log, then the PX4 SITL and real logs of the test fixtures
SHARED_ARDUPILOT = ROOT.parent / "shared" / "data" / "ardupilot"
LOGS = [SHARED_ARDUPILOT / "copter-sitl-4.3.bin", FIX / "sample_px4_events.ulg", FIX / "sample_log_small.ulg"]
ATTACKS = {"bias": {"magnitude": (1.5, 6.0), "duration": (5.0, 20.0)},
           "ramp": {"rate": (0.2, 1.0), "duration": (10.0, 30.0)}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", type=Path, nargs="+", default=LOGS)
    ap.add_argument("--flights", type=int, default=60, help="simulated flights per attack")
    ap.add_argument("--repeat", type=int, default=20, help="replays of each log segment")
    ap.add_argument("--methods", default="chi2,cusum,sprt,bht,cnn,lstm,quadformer")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    from quadformer.config import AttackConfig, SimConfig, merge
    from quadformer.evaluation.metrics import evaluate
    from quadformer.evaluation.protocol import split_flights, tune
    from quadformer.experiments.detection import run_config
    from quadformer.io import set_threads
    from quadformer.logs import read_log
    from quadformer.logs.detect import detect_log, logs_dataset
    from quadformer.logs.noise import estimate_noise
    from quadformer.estimator.online import FilterConfig
    from quadformer.simulation import simulate

    missing = [str(p) for p in args.logs if not p.exists()]
    if missing:
        ap.error(f"no such log: {', '.join(missing)} (the ArduPilot log is in the shared data beside the "
                 "repository, ../shared/data/ardupilot/; give others with --logs)")
    set_threads()
    methods = args.methods.split(",")
    logs = [read_log(p) for p in args.logs]
    noise = estimate_noise(logs)
    print("fleet noise:", {k: round(v, 4) for k, v in noise.to_dict().items() if isinstance(v, float)}, flush=True)
    out: dict = {"logs": [str(p) for p in args.logs], "noise": noise.to_dict(), "attacks": {}}
    for kind, ranges in ATTACKS.items():
        t0 = time.perf_counter()
        cfg = SimConfig.from_dict(merge(noise.sim_overrides(), {
            "model": "II", "noise": "gaussian", "sensors": "gps+imu+mag+baro", "flights": args.flights,
            "duration": 60.0, "seed": args.seed + (1 if kind == "ramp" else 0), "attack": {"kind": kind}}))
        sim = simulate(cfg)
        parts = split_flights(sim.scenarios, args.seed).frames(sim.flights)
        trained = {m: tune(m, parts.train, parts.y_train, parts.val, gps_rate_hz=sim.gps_rate_hz).detector
                   for m in methods}
        replay = FilterConfig.matching(sim.meta["config"])
        attack = AttackConfig(kind=kind, fraction=0.5, onset=(3.0, 10.0), **ranges)
        real = logs_dataset(args.logs, "ekf", replay, attack=attack, seed=args.seed, repeat=args.repeat)
        f = real.flights
        rows = {}
        for m, det in trained.items():
            s = det.decision_function(f)
            res = evaluate(f.flight_id.to_numpy(), f.t.to_numpy(), f.label.to_numpy(), s, s > det.threshold_,
                           gps_rate_hz=real.gps_rate_hz)
            # false alarms on the clean logs themselves, each counted once
            alarms, steps = 0, 0
            for log in logs:
                d = detect_log(log, det, "ekf", replay)
                alarms += len(d.alerts)
                steps += len(d.rows)
            rows[m] = {"sim_event_recall": res["event_recall"], "sim_delay_median_s": res["delay_median_s"],
                       "sim_f1": res["f1"], "clean_log_alarms": alarms,
                       "clean_log_hours": steps / real.gps_rate_hz / 3600,
                       "clean_log_alarms_per_hour": alarms / (steps / real.gps_rate_hz / 3600)}
        # trained on the injected logs: split by recording, so the training part may be one log's
        # replays; every label of the training recordings is used (a fifth of one recording is none)
        try:
            on_real, _ = run_config(real, methods, seed=args.seed, label_fraction=1.0)
        except ValueError as e:
            on_real = {"split": {"test": 0}, "methods": {m: {"event_recall": float("nan"), "f1": float("nan"),
                                                             "false_alarms_per_hour": None} for m in methods},
                       "error": str(e)}
            print(f"trained on the logs: not possible here: {e}", flush=True)
        for m in methods:
            r = on_real["methods"][m]
            rows[m].update(real_event_recall=r["event_recall"], real_f1=r["f1"],
                           real_false_alarms_per_hour=r["false_alarms_per_hour"])
        out["attacks"][kind] = {"sim_flights": args.flights, "real_flights": int(len(real.scenarios)),
                                "real_attacked": int(real.scenarios.attacked.sum()),
                                "real_test_flights": on_real["split"]["test"], "methods": rows,
                                "seconds": time.perf_counter() - t0}
        print(f"\n{kind}: {len(real.scenarios)} replayed flights ({int(real.scenarios.attacked.sum())} attacked); "
              f"clean logs {rows[methods[0]]['clean_log_hours'] * 3600:.0f} s", flush=True)
        print(f"{'method':12s} {'sim->real evR':>14s} {'delay s':>8s} {'F1':>6s} {'FA on clean logs':>17s}"
              f" {'real->real evR':>15s} {'F1':>6s}")
        for m, r in rows.items():
            delay = "-" if r["sim_delay_median_s"] is None else f"{r['sim_delay_median_s']:.1f}"
            print(f"{m:12s} {r['sim_event_recall']:14.2f} {delay:>8s} {r['sim_f1']:6.2f} "
                  f"{r['clean_log_alarms']:>5d} ({r['clean_log_alarms_per_hour']:6.1f}/h) "
                  f"{r['real_event_recall']:15.2f} {r['real_f1']:6.2f}", flush=True)
    print(json.dumps({"benchmark": "sim_to_real", **out}, default=float))


if __name__ == "__main__":
    main()
