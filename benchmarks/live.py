"""Live monitor speed and memory: a long flight streamed as fast as the monitor keeps up.

A simulated flight without a camera (Model I, hover, gps+imu+mag+baro, 60 s) is looped end
to end (time continues; positions continue from where the previous loop ended) by the test
sender in its own process, over UDP on 127.0.0.1 with TIMESYNC flow control, to a monitor in
this process (``bht`` fit on two other simulated flights; the filter fuses GPS, IMU and the
magnetometer, as the demo's). Reported:

- resident memory (RSS) after a warm-up (``--warmup`` s of vehicle time) and at the end, and
  its growth;
- per-fix processing latency (the monitor's histogram: from the message in hand to the
  admission decision), p50 and p99;
- messages per second and vehicle seconds per wall second while streaming, and the
  monitor's CPU time per message.

The last line printed is one JSON object.

    python benchmarks/live.py [--hours 1.0] [--warmup 300]
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing as mp
import os
import threading
import time


def rss_mb() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def play(streams, port: int, loops: int, queue) -> None:
    import torch

    from quadformer.sender import SenderConfig, send

    torch.set_num_threads(1)
    rep = send(streams, f"udpout:127.0.0.1:{port}", SenderConfig(loops=loops, window=256,
                                                                 timeout_s=loops * 60.0 + 600.0))
    queue.put({"sent": rep.sent, "stalls": rep.stalls, "wall_s": rep.wall_s, "vehicle_s": rep.vehicle_s,
               "timed_out": rep.timed_out})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=float, default=1.0, help="vehicle time to stream")
    ap.add_argument("--warmup", type=float, default=300.0, help="s of vehicle time before the first RSS sample")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    import numpy as np
    import pandas as pd
    import torch

    from quadformer.config import MissionConfig, SimConfig
    from quadformer.estimator.online import FilterConfig
    from quadformer.live.monitor import Monitor, MonitorConfig
    from quadformer.sender import VehicleStreams
    from quadformer.simulation import simulate_batch

    torch.set_num_threads(1)
    cfg = SimConfig(model="I", sensors="gps+imu+mag+baro", flights=3, duration=60.0, seed=args.seed,
                    mission=MissionConfig(kinds=("hover",)))
    t0 = time.perf_counter()
    sim = simulate_batch(cfg, np.arange(3), np.zeros(3, bool), record_sensors=True)
    n = len(sim["t"])
    table = pd.DataFrame({"flight_id": np.repeat([1, 2], n), "t": np.tile(sim["t"], 2),
                          "label": np.zeros(2 * n, np.int8), "res_gps_nis": sim["res_gps_nis"][1:, :, 0].reshape(-1)})
    det = make_detector(table)
    print(f"simulated and fit in {time.perf_counter() - t0:.0f} s", flush=True)
    streams = VehicleStreams.from_simulation(sim["sensors"], flight=0)
    loops = max(1, math.ceil(args.hours * 3600.0 / cfg.duration))

    marks: dict[str, float] = {}
    state = {"next_print": time.perf_counter() + 60.0}

    def on_fix(rec) -> None:
        now = time.perf_counter()
        marks.setdefault("first_fix", now)
        marks.setdefault("t0", rec.t)
        marks["last_fix"], marks["t_last"] = now, rec.t
        if "rss_warm" not in marks and rec.t - marks["t0"] >= args.warmup:
            marks["rss_warm"] = rss_mb()
            marks["warm_at"] = now
            marks["cpu_warm"] = time.process_time()
            marks["msgs_warm"] = mon.n_messages
        if now >= state["next_print"]:
            state["next_print"] = now + 60.0
            print(f"  vehicle {rec.t - marks['t0']:7.0f} s, {mon.fixes} fixes, RSS {rss_mb():.1f} MiB, "
                  f"{mon.n_messages / (now - marks['first_fix']):.0f} msg/s", flush=True)

    filt = FilterConfig.matching(cfg.to_dict(), sensors="gps+imu+mag")
    config = MonitorConfig(connect="udpin:127.0.0.1:0", filter=filt, status_s=3600.0,
                           duration_s=loops * cfg.duration + 900.0)
    mon = Monitor(det, config, on_fix=on_fix, echo=None)
    mon.open()
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=play, args=(streams, mon.address[1], loops, queue), daemon=True)
    proc.start()

    sender_result: dict = {}

    def wait_sender() -> None:
        sender_result.update(queue.get(timeout=loops * 60.0 + 900.0))
        marks["rss_end"] = rss_mb()
        mon.stop()

    waiter = threading.Thread(target=wait_sender, daemon=True)
    waiter.start()
    summary = mon.run()
    cpu_end = time.process_time()
    proc.join(30)
    waiter.join(5)
    stream_wall = marks["last_fix"] - marks["first_fix"]
    steady_wall = marks["last_fix"] - marks.get("warm_at", marks["first_fix"])
    steady_msgs = summary["n_messages"] - marks.get("msgs_warm", 0)
    vehicle = marks["t_last"] - marks["t0"]
    out = {
        "vehicle_s": vehicle, "stream_wall_s": stream_wall, "realtime_factor": vehicle / stream_wall,
        "messages": summary["n_messages"], "messages_per_s": summary["n_messages"] / stream_wall,
        "fixes": summary["fixes_scored"], "alerts": summary["alerts_total"], "segments": summary["segments"],
        "errors": summary["errors"], "lost_packets": summary["link"]["lost_packets"],
        "latency_ms_p50": summary["latency_ms"]["p50"], "latency_ms_p99": summary["latency_ms"]["p99"],
        "latency_ms_max": summary["latency_ms"]["max"],
        "cpu_ms_per_message": 1e3 * (cpu_end - marks.get("cpu_warm", 0.0)) / max(steady_msgs, 1),
        "steady_messages_per_s": steady_msgs / steady_wall if steady_wall > 0 else math.nan,
        "rss_warm_mb": marks.get("rss_warm"), "rss_end_mb": marks.get("rss_end"),
        "rss_growth_pct": 100.0 * (marks["rss_end"] / marks["rss_warm"] - 1.0) if "rss_warm" in marks else None,
        "warmup_vehicle_s": args.warmup, "sender": sender_result, "torch_threads": torch.get_num_threads(),
        "cpus": os.cpu_count(),
    }
    print(json.dumps(out))


def make_detector(table):
    """BHT fit on one clean simulated flight, its threshold the 99.9th percentile of another's
    scores (this measures speed, not detection quality)."""
    import numpy as np

    from quadformer.detectors import make

    det = make("bht").fit(table[table.flight_id == 1])
    thr = float(np.quantile(det.decision_function(table[table.flight_id == 2]), 0.999))
    det.calibrate(thr, thr)
    return det


if __name__ == "__main__":
    main()
