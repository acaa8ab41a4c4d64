"""Live spoof detection on a real flight: a log's sensors streamed to the monitor, spoofed or not.

A real flight log (by default an ArduCopter flight of the real-flights set, read from
``../shared``; the repository holds no such log) is played by the test sender in its own process
over UDP on 127.0.0.1 (TIMESYNC flow control: as fast as the monitor keeps up), with the vehicle's
arming and take-off / landing from the log's events, to the monitor in this process, set up as
``quadformer monitor`` sets itself up without ``--model``: the shipped detector chosen for the
sensors the log sends (``--sensors`` overrides), the filter of the simulation it was trained on,
shape typing. Optionally a spoof is injected into the GPS before it is sent
(``VehicleStreams.with_attack``), its onset on the log's clock (s from its first sample):

    python benchmarks/live_spoof.py                                   # clean
    python benchmarks/live_spoof.py --attack drift --rate 1.0 --onset 90 --onset-step
    python benchmarks/live_spoof.py --attack drift --rate 1.0 --accel 0.2 --onset 90 --accelerating
    python benchmarks/live_spoof.py --attack capture --magnitude 8 --rate 1.5 --onset 90

The last line printed is one JSON object: the alerts raised (kind, phase, reason, time on the
log's clock, type), the spoofing alerts raised in the air (on a clean run: its false alarms), and
with a spoof the time from its onset to the first spoofing alert in the air after it (a fix is
scored at its epoch, its read delay before its stamp: an alert up to half a receiver period
before the onset is the onset fix's, and counted as at the onset).
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing as mp
import shutil
import tempfile
import threading
import time
from pathlib import Path

DEFAULT_LOG = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "real-flights" / \
    "joeydouglas_2014-10-18_20-04-24.bin"


def play(streams, port: int, config, queue) -> None:
    from quadformer.sender import send

    rep = send(streams, f"udpout:127.0.0.1:{port}", config)
    queue.put({"sent": rep.sent, "data": rep.data, "stalls": rep.stalls, "wall_s": rep.wall_s,
               "vehicle_s": rep.vehicle_s, "timed_out": rep.timed_out})


def spans(events) -> tuple[tuple[float, float] | None, tuple[float, float] | None]:
    """(armed, in air) spans on the log's clock from its events: the first arming to the last
    disarming, the first take-off to the last landing (in the air to the end where a take-off
    follows the last landing; None where the log says nothing)."""
    if events is None:
        return None, None
    t = {e: events.loc[events.event == e, "t"].to_numpy() for e in ("armed", "disarmed", "takeoff", "landed")}
    armed = (float(t["armed"][0]), float(t["disarmed"][-1]) if len(t["disarmed"]) else math.inf) \
        if len(t["armed"]) else None
    landed = float(t["landed"][-1]) if len(t["landed"]) and t["landed"][-1] > t["takeoff"][-1] else math.inf
    air = (float(t["takeoff"][0]), landed) if len(t["takeoff"]) else None
    return armed, air


def make_attack(args, end: float):
    """The one-flight AttackBatch of the options, its times on the log's clock."""
    import numpy as np

    from quadformer.attacks import sample_attacks
    from quadformer.config import AttackConfig
    from quadformer.rng import Stream, batch_generators

    def fixed(v):
        return None if v is None else (float(v), float(v))

    cfg = AttackConfig(kind=args.attack, fraction=1.0, onset=fixed(args.onset), duration=fixed(end - args.onset),
                       magnitude=fixed(args.magnitude), rate=fixed(args.rate), accel=fixed(args.accel),
                       onset_step=args.onset_step, capture_s=fixed(args.capture_s),
                       lock_loss_s=fixed(args.lock_loss), axes=args.axes)
    return sample_attacks(batch_generators(args.seed, np.arange(1), Stream.SCENARIO), cfg, np.ones(1, bool),
                          end + 1.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("log", nargs="?", type=Path, default=DEFAULT_LOG, help="a flight log (default: %(default)s)")
    ap.add_argument("--attack", default=None, help="an attack kind (drift, capture, ramp, bias, ...); none: clean")
    ap.add_argument("--onset", type=float, default=90.0, help="s on the log's clock")
    ap.add_argument("--rate", type=float, default=None, help="m/s (ramp, drift, capture)")
    ap.add_argument("--accel", type=float, default=None, help="m/s^2 (an accelerating drift)")
    ap.add_argument("--onset-step", dest="onset_step", action="store_true", default=None,
                    help="drift: the velocity steps to the rate at the onset")
    ap.add_argument("--accelerating", dest="onset_step", action="store_false", help="drift: ramps in at --accel")
    ap.add_argument("--magnitude", type=float, default=None, help="m (bias, capture)")
    ap.add_argument("--capture-s", type=float, default=None, help="s, a capture's pull-off")
    ap.add_argument("--lock-loss", type=float, default=None, help="s, a capture's lost lock")
    ap.add_argument("--axes", default=None, help="attacked axes, e.g. x (default: drawn)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the attack's drawn parameters")
    ap.add_argument("--sensors", default=None, help="sensors the monitor fuses (default: those the log sends)")
    ap.add_argument("--timeout", type=float, default=900.0, help="wall-clock bound (s)")
    ap.add_argument("--gps-delay", dest="gps_delay", type=float, default=None,
                    help="s, each fix fused this long before its stamp (default: the --vehicle profile's, else "
                         "estimated from the link in the air, as quadformer monitor)")
    ap.add_argument("--vehicle", type=Path, default=None,
                    help="a vehicle profile (quadformer calibrate --profile): its detector and receiver latency")
    ap.add_argument("--fixes", type=Path, default=None,
                    help="also write the monitor's fixes.csv (every scored fix) here")
    args = ap.parse_args()

    import numpy as np
    import torch

    from quadformer.detectors import pretrained
    from quadformer.estimator.filter_config import FilterConfig
    from quadformer.live.monitor import Monitor, MonitorConfig
    from quadformer.sender import SenderConfig, VehicleStreams
    from quadformer.logs import read_log
    from quadformer.logs.replay import log_sensors

    torch.set_num_threads(1)
    # the fixes at the stamps the autopilot logged them with, as its link sends them (not at the
    # receiver's epochs, which a link does not carry)
    log = read_log(args.log, **({"epochs": False} if str(args.log).lower().endswith(".bin") else {}))
    streams = VehicleStreams.from_log(log)
    end = streams.end
    attack = None
    if args.attack not in (None, "none"):
        attack = make_attack(args, end)
        streams = streams.with_attack(attack, t0=0.0)
    have = set((args.sensors or "+".join(log_sensors(log))).split("+"))
    entry = pretrained.choose(have, "ekf", None)              # as `quadformer monitor` chooses without --model
    delay = args.gps_delay
    if args.vehicle is not None:                              # as `quadformer monitor --vehicle`
        from quadformer.detectors import load

        det = load(args.vehicle)
        sensors = det.calibration_["vehicle_sensors"]
        if delay is None:
            delay = det.calibration_.get("vehicle_gps_delay_s")
        label = str(args.vehicle)
    else:
        det = pretrained.load(entry.name)
        sensors = args.sensors or pretrained.fused_sensors(entry, have)
        label = f"shipped:{entry.name}"
    filt = FilterConfig.matching(det.calibration_["sim_config"], sensors=sensors, min_segment_s=3.0,
                                 receiver_accuracy=True, gps_delay_s=delay)
    armed, air = spans(log.events)
    start = streams.start
    sender = SenderConfig(window=256, timeout_s=args.timeout, autopilot="ardupilot",
                          armed=armed, in_air=air if air is not None else None)
    alerts: list[dict] = []
    scored = Path(tempfile.mkdtemp(prefix="live_spoof_"))
    config = MonitorConfig(connect="udpin:127.0.0.1:0", filter=filt, status_s=3600.0, duration_s=args.timeout + 30.0,
                           out=scored)
    mon = Monitor(det, config, on_alert=alerts.append, echo=None, model=label)
    mon.open()
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=play, args=(streams, mon.address[1], sender, queue), daemon=True)
    t_wall = time.perf_counter()
    proc.start()
    result: dict = {}

    def wait_sender() -> None:
        try:
            result.update(queue.get(timeout=args.timeout + 60.0))
        finally:
            mon.stop()

    waiter = threading.Thread(target=wait_sender, daemon=True)
    waiter.start()
    summary = mon.run()
    proc.join(30)
    waiter.join(5)
    raised = [{"kind": e["kind"], "phase": e["phase"], "reason": e["reason"], "t_s": e["vehicle_t"] + start,
               "onset_s": e["onset_s"] + start, "attack_type": e["attack_type"], "score": e["score"]}
              for e in alerts if e["event"] == "alert_start"]
    in_air = [a for a in raised if a["kind"] == "spoofing" and a["phase"] == "air"]
    import pandas as pd

    fixes = pd.read_csv(scored / "fixes.csv")
    fixes["t"] += start
    if args.fixes is not None:
        fixes.to_csv(args.fixes, index=False)
    shutil.rmtree(scored, ignore_errors=True)
    out = {"log": Path(args.log).name, "detector": label, "method": det.name, "sensors": sensors,
           "gps_delay_s": summary["gps_delay"]["s"], "gps_delay_source": summary["gps_delay"]["source"],
           "gps_epochs": summary["gps_epochs"],
           "largest_score_in_air": float(fixes.loc[fixes.phase == "air", "score"].max()),
           "threshold": float(det.threshold_), "in_air_s": air, "attack": None, "alerts": raised,
           "spoofing_alerts_in_air": len(in_air), "fixes_scored": summary["fixes_scored"],
           "wall_s": time.perf_counter() - t_wall, "sender": result}
    if attack is not None:
        fields = ("onset", "end", "magnitude", "rate", "accel", "capture_s", "lock_loss_s")
        out["attack"] = {"kind": str(attack.kind[0]), "axes": str(attack.axes[0]),
                         "direction": [float(v) for v in attack.direction[0]],
                         "onset_step": bool(attack.onset_step[0]) if attack.kind[0] == "drift" else None,
                         **{f: (float(getattr(attack, f)[0]) if np.isfinite(getattr(attack, f)[0]) else None)
                            for f in fields}}
        onset, stop = float(attack.onset[0]), float(attack.end[0])
        # the monitor fuses a fix at its epoch, its read delay (tens of ms) before the stamp the spoof's
        # onset is counted on: the onset's fix may be scored up to that much before the onset
        ts = fixes["t"].to_numpy(dtype=float)
        from_t = onset - 0.5 * (float(np.median(np.diff(ts))) if len(ts) > 1 else 0.0)
        after = [a["t_s"] for a in in_air if from_t <= a["t_s"] < stop]
        out["spoofing_alerts_in_air_before_onset"] = sum(a["t_s"] < from_t for a in in_air)
        out["first_spoofing_in_air_after_onset_s"] = (max(0.0, min(after) - onset)) if after else None
        near = fixes[(fixes.t >= from_t) & (fixes.t <= onset + 10.0)]
        out["largest_score_10s_after_onset"] = float(near["score"].max()) if len(near) else None
        before = fixes[(fixes.t < from_t) & (fixes.phase == "air")]
        out["largest_score_in_air_before_onset"] = float(before["score"].max()) if len(before) else None
    print(json.dumps(out))


if __name__ == "__main__":
    main()
