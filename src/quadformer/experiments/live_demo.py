"""The live monitor's demo: a detector fit in seconds on simulated flights without a camera,
then a simulated spoofed flight streamed as MAVLink from a sender on 127.0.0.1 to a monitor,
which shows the alert arriving. About half a minute on a laptop core.

The training flights and the demo flight are simulated in one batch (flight i's data depend
only on the seed and i). The detector (``bht`` by default: the GPS NIS, no network) is tuned on
the training flights' residues (train / validation by flight). The monitor's filter takes the
simulation's tuning and fuses GPS, IMU and the magnetometer: over MAVLink the GPS gives no
vertical velocity (GPS_RAW_INT) and the barometer's offset is fixed at the first fix, so the
vertical channel is left to GPS (the NIS then keeps the scale the detector was fit on). The
simulated vehicle flies from its first sample: the sender says so (armed and in the air from
then), so the monitor's flight phase is the take-off transition for its first 5 s, then the air.
"""

from __future__ import annotations

import math
import threading
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pandas as pd

from quadformer.config import AttackConfig, SimConfig
from quadformer.estimator.online import FilterConfig
from quadformer.estimator.schema import RESIDUES, groups_for
from quadformer.evaluation.protocol import tune
from quadformer.live.monitor import Monitor, MonitorConfig
from quadformer.sender import SenderConfig, VehicleStreams, send
from quadformer.simulation import simulate_batch

TRAIN_FLIGHTS = 6          # the demo flight is the next index
DEMO_SENSORS = "gps+imu+mag"


def demo_config(seed: int = 0) -> SimConfig:
    return SimConfig(model="I", noise="gaussian", sensors="gps+imu+mag+baro", flights=TRAIN_FLIGHTS + 1,
                     duration=30.0, seed=seed,
                     attack=AttackConfig(kind="bias", onset=(10.0, 12.0), duration=(8.0, 10.0), magnitude=(5.0, 6.0)))


def _residue_table(sim, cfg: SimConfig, flights: range) -> pd.DataFrame:
    names = [g for g in groups_for(cfg.sensors) if g in RESIDUES]
    n = len(sim["t"])
    cols: dict[str, Any] = {"flight_id": np.repeat(np.asarray(list(flights), dtype=np.int32), n),
                            "t": np.tile(sim["t"], len(flights)),
                            "label": sim["label"][list(flights)].reshape(-1).astype(np.int8)}
    for g in names:
        for i, c in enumerate(g.columns):
            cols[c] = sim[g.name][list(flights), :, i].reshape(-1)
    return pd.DataFrame(cols)


def run_demo(out: Path | None = None, detector=None, method: str = "bht", speed: float = 5.0,
             duration_s: float | None = None, seed: int = 0, act: bool = False,
             echo: Callable[[str], None] = print, model_path: str | None = None) -> dict[str, Any]:
    """Fit (unless ``detector`` is given), stream the spoofed flight, monitor it; the monitor's
    summary. ``out``: the monitor's outputs and the fitted model (demo-model.json)."""
    cfg = demo_config(seed)
    attacked = np.array([i % 2 == 0 for i in range(TRAIN_FLIGHTS)] + [True])
    echo(f"demo: simulating {TRAIN_FLIGHTS} training flights and one spoofed flight "
         f"({cfg.duration:g} s each, {cfg.sensors}) ...")
    sim = simulate_batch(cfg, np.arange(TRAIN_FLIGHTS + 1), attacked, record_sensors=True)
    if detector is None:
        table = _residue_table(sim, cfg, range(TRAIN_FLIGHTS))
        train, val = table[table.flight_id < 4], table[table.flight_id >= 4]
        tuned = tune(method, train, train["label"].to_numpy(), val)
        detector = tuned.detector
        detector.calibrate(detector.threshold_, detector.budget_threshold_, sim_config=cfg.to_dict(),
                           data="quadformer monitor --demo")
        echo(f"demo: {method} fit on {TRAIN_FLIGHTS} flights: params {tuned.params}, threshold "
             f"{detector.threshold_:.4g} (validation F1 {tuned.val_f1:.2f})")
        if out is not None:
            model_path = str(detector.save(Path(out) / "demo-model.json"))
    a, k = sim["attacks"], TRAIN_FLIGHTS
    t0 = float(sim["sensors"]["imu_t"][0])          # the monitor's t counts from the first sample
    echo(f"demo: the spoofed flight: GPS offset by {a.magnitude[k]:.1f} m from t {a.onset[k] - t0:.1f} s to "
         f"{a.end[k] - t0:.1f} s (from the first sensor sample), streamed at {speed:g}x real time")
    config = MonitorConfig(connect="udpin:127.0.0.1:0",
                           filter=FilterConfig.matching(cfg.to_dict(), sensors=DEMO_SENSORS),
                           out=out, duration_s=duration_s, act=act)
    monitor = Monitor(detector, config, echo=echo, model=model_path)
    monitor.open()
    streams = VehicleStreams.from_simulation(sim["sensors"], flight=k)
    done = threading.Event()

    def play() -> None:
        try:
            send(streams, f"udpout:127.0.0.1:{monitor.address[1]}",
                 SenderConfig(speed=speed, timeout_s=cfg.duration / speed + 60.0, armed=(0.0, math.inf),
                              in_air=(0.0, math.inf)), stop=done)
        finally:
            monitor.stop()

    sender = threading.Thread(target=play, name="demo-sender", daemon=True)
    sender.start()
    try:
        summary = monitor.run()
    finally:
        done.set()
        sender.join(5.0)
    return summary
