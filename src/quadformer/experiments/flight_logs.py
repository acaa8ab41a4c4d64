"""Simulated flights as autopilot flight logs (``simulate --export ulog,dataflash``).

One flight of a batch (``simulate_batch(..., record_sensors=True)``) becomes a ``FlightLog``
(``flight_log``) that the log writers turn into a PX4 ULog or an ArduPilot DataFlash file,
which PX4 Flight Review, MAVExplorer, PlotJuggler and this project's readers open:

* sensors at their simulated rates: IMU (100 Hz: specific force and body rate), GPS (the fix
  the vehicle received: spoofed during an attack), and the configured magnetometer,
  barometer (height above the origin) and VIO (velocity, attitude, and its odometry-frame
  position, which the simulator records at the GPS steps, linearly interpolated to the VIO
  times and held before the first);
* at each GPS step, the in-loop filter's attitude and position/velocity estimate after the
  update, its GPS innovations as the autopilots log them (predicted minus measured), their
  variances (the predicted innovation variance, the diagonal of S) and test ratios
  (innovation^2 / (5^2 variance), the largest over the horizontal axes for position and over
  the three axes for velocity: PX4's per-axis ratios as its reader gives them back); each
  writer writes its own autopilot's ratios from the innovations and variances (PX4: per axis;
  ArduPilot: summed over a group's axes, ``logs.ardupilot_ratios``), and the simulator's truth
  (position, velocity, attitude);
* positions geodetic about ``ORIGIN``; the receiver states the configured GPS error as its
  accuracy (eph, epv: the white and the slow error together; speed accuracy: the velocity
  noise), ``SATELLITES`` satellites and a noise level of ``NOISE`` (PX4's ``noise_per_ms``), and
  reports each fix in the ``receiver`` stream too. Under a capture the receiver reports what a
  captured receiver does (``AttackBatch.receiver_effects``): its satellites drop and recover, its
  accuracies inflate for seconds, its noise rises, and the fixes of its brief loss of lock are
  reports without a fix (fix type 1, in the receiver stream only; the simulated vehicle fused
  them, the simulation has no receiver of its own to lose them).

How the sensors are logged is ``LogConditions`` (``logs.conditions``: the IMU's logging rate,
instantaneous samples of a vibrating airframe or integrated deltas, the GPS's logging rate,
latency and read jitter); off by default, the sensors logged as simulated. Its random draws come
from each flight's own ``Stream.LOG`` generator (``quadformer.rng``): a flight's log depends only
on the dataset's seed and its flight id.

The flights start airborne (the simulator starts each flight in the air at its mission's
first point): each log starts armed and flying. The vehicle's clock reads ``BOOT_T0`` at the
flight's t = 0 and the GPS time ``UTC0`` + t. An attacked flight's attack (kind, onset, end,
magnitude, axes) goes to a JSON note beside its logs.
"""

from __future__ import annotations

import math
import tempfile
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from quadformer.config import SimConfig
from quadformer.dataset import Dataset, write_dataset
from quadformer.geometry import frames
from quadformer.io import write_json
from quadformer.logs import FlightLog
from quadformer.logs.conditions import LogConditions, apply_conditions
from quadformer.logs.dataflash_writer import write_dataflash
from quadformer.logs.flightlog import make_stream
from quadformer.logs.ulog_writer import write_ulog
from quadformer.logs.writing import GATE, LogHeader
from quadformer.rng import Stream, flight_generator

__all__ = ["BOOT_T0", "CONDITIONS_FILE", "EXPORT_FORMATS", "NOISE", "ORIGIN", "SATELLITES", "SUFFIX", "UTC0",
           "LogExport", "attack_note", "check_conditions", "export_formats", "flight_log", "simulate_with_logs"]

ORIGIN = (47.397742, 8.545594, 488.0)   # lat deg, lon deg, alt m (AMSL) of the simulator's ENU origin
BOOT_T0 = 10.0                          # s, the vehicle's clock (time since boot) at the flight's t = 0
UTC0 = 1_704_067_200.0                  # s, UNIX time at t = 0 (2024-01-01 00:00 UTC), for GPS times
SATELLITES = 12                         # satellites a clean simulated receiver uses
NOISE = 100                             # its noise level (PX4 noise_per_ms)
EXPORT_FORMATS = ("ulog", "dataflash")
SUFFIX = {"ulog": ".ulg", "dataflash": ".bin"}
WRITERS = {"ulog": write_ulog, "dataflash": write_dataflash}
CONDITIONS_FILE = "log_conditions.json"   # beside the logs, when they are logged under conditions


def export_formats(values: Iterable[str]) -> tuple[str, ...]:
    """The log formats named by ``values`` (each one name or a comma list), in
    ``EXPORT_FORMATS`` order; ValueError naming the choices for an unknown one."""
    names = [v.strip().lower() for text in values for v in str(text).split(",") if v.strip()]
    unknown = [v for v in names if v not in EXPORT_FORMATS]
    if unknown:
        raise ValueError(f"--export: unknown log format {unknown[0]!r}; choose from {', '.join(EXPORT_FORMATS)} "
                         "(repeat the option or join them with commas)")
    return tuple(f for f in EXPORT_FORMATS if f in names)


def _np(x) -> np.ndarray:
    return x.numpy() if hasattr(x, "numpy") else np.asarray(x)


def _quat(q: np.ndarray) -> dict[str, np.ndarray]:
    q = frames.quat_normalize(q)
    return {"qx": q[:, 0], "qy": q[:, 1], "qz": q[:, 2], "qw": q[:, 3]}


def _xyz(prefix: str, v: np.ndarray) -> dict[str, np.ndarray]:
    return {f"{prefix}{a}": v[:, k] for k, a in enumerate("xyz")}


def flight_log(cfg: SimConfig, r, i: int, origin: tuple[float, float, float] = ORIGIN,
               path: str | Path = "simulated") -> FlightLog:
    """Flight ``i`` (its index in the batch) of ``r``, a ``simulate_batch`` result with the raw
    sensor streams recorded, as a FlightLog (see the module docstring). Times are the
    simulator's (s from the flight's start); the vehicle's clock is ``BOOT_T0`` + t."""
    s = r.get("sensors")
    if s is None or "true_q" not in s:
        raise ValueError("flight_log needs a batch simulated with record_sensors=True")
    streams = {**_sensors(cfg, r, i, origin), **_filter_and_truth(r, i)}
    end = float(max(df["t"].iloc[-1] for df in streams.values()))
    return FlightLog(source="arrays", path=Path(path), vehicle={"autopilot": "quadformer simulator"},
                     notes=["simulated: the flight starts airborne, armed and flying"], origin=tuple(origin),
                     origin_source="autopilot local origin", segments=[(0.0, end)], boot_t0=BOOT_T0, **streams)


def _sensors(cfg: SimConfig, r, i: int, origin: tuple[float, float, float]) -> dict:
    """The raw sensor streams of flight i: IMU, GPS as received, and the configured aiding sensors."""
    s = r["sensors"]
    t_gps = np.asarray(s["gps_t"], dtype=float)
    gps = _np(s["gps"][i]).astype(float)
    lla = frames.enu_to_geodetic(gps[:, :3], origin)
    imu = _np(s["imu"][i]).astype(float)
    status = _receiver(cfg, r, i, t_gps)
    fix = status["fix_type"] >= 2
    out = {
        "imu": make_stream("imu", s["imu_t"], dict(zip(("ax", "ay", "az", "gx", "gy", "gz"), imu.T))),
        "gps": make_stream("gps", t_gps[fix], {
            **_xyz("", gps[fix, :3]), **_xyz("v", gps[fix, 3:]), "lat": lla[fix, 0], "lon": lla[fix, 1],
            "alt": lla[fix, 2], **{k: v[fix] for k, v in status.items() if k != "noise"}}),
        "receiver": make_stream("receiver", t_gps, status),
    }
    if "mag" in s:
        out["mag"] = make_stream("mag", s["mag_t"], dict(zip(("mx", "my", "mz"), _np(s["mag"][i]).astype(float).T)))
    if "baro" in s:
        out["baro"] = make_stream("baro", s["baro_t"], {"alt": _np(s["baro"][i])[:, 0].astype(float)})
    if "vio" in s:                       # its odometry-frame position is recorded at the GPS steps
        vt = np.asarray(s["vio_t"], dtype=float)
        vio = _np(s["vio"][i]).astype(float)
        pos = np.column_stack([np.interp(vt, t_gps, r["vio_pos"][i][:, k]) for k in range(3)])
        out["odometry"] = make_stream("odometry", vt, {**_xyz("", pos), **_xyz("v", vio[:, :3]), **_quat(vio[:, 3:7])})
    return out


def _receiver(cfg: SimConfig, r, i: int, t_gps: np.ndarray) -> dict[str, np.ndarray]:
    """What the receiver of flight i reports at each GPS step: a clean receiver's constant
    values, changed by a capture's effects (``AttackBatch.receiver_effects``)."""
    g = cfg.gps
    fx = {k: v[:, i] for k, v in r["attacks"].receiver_effects(t_gps).items()}
    eph, epv = math.hypot(g.pos_std_h, g.gm_std), math.hypot(g.pos_std_v, g.gm_std)
    return {"fix_type": np.where(fx["fix_lost"], 1.0, 3.0), "satellites": np.round(SATELLITES * fx["satellites"]),
            "eph": eph * fx["eph"], "epv": epv * fx["epv"], "speed_acc": g.vel_std * fx["speed_acc"],
            "noise": np.round(NOISE * fx["noise"])}


def _filter_and_truth(r, i: int) -> dict:
    """At each GPS step: the in-loop filter's attitude, estimate and innovations, and the truth."""
    s = r["sensors"]
    t_gps = np.asarray(s["gps_t"], dtype=float)
    return {
        "estimate": make_stream("estimate", t_gps, {**_xyz("", r["est_pos"][i]), **_xyz("v", r["est_vel"][i])}),
        "attitude": make_stream("attitude", t_gps, _quat(_np(s["est_q"][i]).astype(float))),
        "innovations": _innovations(r, i, t_gps),
        "truth": make_stream("truth", t_gps, {**_xyz("", r["true_pos"][i]), **_xyz("v", r["true_vel"][i]),
                                              **_quat(_np(s["true_q"][i]).astype(float))}),
    }


def _innovations(r, i: int, t_gps: np.ndarray):
    """The in-loop filter's GPS innovations as the autopilots log them: predicted minus measured."""
    inn = -np.asarray(r["res_gps_r"][i], dtype=float)
    var = np.asarray(r["res_gps_s"][i], dtype=float) ** 2
    ratio = inn ** 2 / (GATE ** 2 * var)
    values = {"ratio_pos": ratio[:, :2].max(axis=1), "ratio_vel": ratio[:, 3:].max(axis=1), "ratio_hgt": ratio[:, 2]}
    for k, a in enumerate("xyz"):
        values.update({f"pos_{a}": inn[:, k], f"vel_{a}": inn[:, 3 + k], f"var_pos_{a}": var[:, k],
                       f"var_vel_{a}": var[:, 3 + k]})
    return make_stream("innovations", t_gps, values)


#: the parameters of its own each attack kind has, beside onset, end, magnitude and axes
KIND_PARAMETER = {"ramp": (("rate", "rate_m_s"),), "sinusoid": (("frequency", "frequency_hz"),),
                  "intermittent": (("period", "period_s"),), "replay": (("delay", "delay_s"),),
                  "drift": (("rate", "rate_m_s"), ("accel", "accel_m_s2"), ("onset_step", "onset_step")),
                  "capture": (("rate", "rate_m_s"), ("capture_s", "capture_s"), ("lock_loss_s", "lock_loss_s"),
                              ("sat_share", "satellites_share"), ("eph_gain", "eph_gain"),
                              ("speed_acc_gain", "speed_acc_gain"), ("noise_rise", "noise_rise"),
                              ("recover_s", "recover_s"))}


def attack_note(r, i: int) -> dict | None:
    """The attack on flight ``i`` of batch ``r`` (None when it is not attacked): kind, onset, end
    (s from the flight's start, and on the logs' clock), magnitude, axes, direction and the
    kind's own parameters (a ramp's rate, a sinusoid's frequency, a capture's pull-off time and
    receiver effects, ...)."""
    a = r["attacks"]
    if not bool(a.attacked[i]):
        return None
    kind = str(a.kind[i])
    note = {"flight_id": int(r["flights"][i]), "attack_type": kind, "onset_s": float(a.onset[i]),
            "end_s": float(a.end[i]), "onset_boot_s": BOOT_T0 + float(a.onset[i]),
            "end_boot_s": BOOT_T0 + float(a.end[i]), "magnitude_m": float(a.magnitude[i]), "axes": str(a.axes[i]),
            "direction": [float(v) for v in a.direction[i]]}
    for field, key in KIND_PARAMETER.get(kind, ()):
        v = getattr(a, field)[i]
        note[key] = bool(v) if field == "onset_step" else float(v)
    note["gps"] = "the GPS in the logs is the spoofed fix the vehicle received"
    note["time"] = "onset_s/end_s count from the flight's start; *_boot_s are the logs' clock (time since boot)"
    return note


def check_conditions(cfg: SimConfig, conditions: LogConditions) -> tuple[int, int]:
    """(IMU, GPS) simulated samples per logged one under ``conditions`` for flights of ``cfg``;
    ValueError naming the rate when a logging rate is faster than the simulated one (IMU
    1 / ``cfg.dt``, GPS ``cfg.gps.rate_hz``) or does not divide it."""
    return conditions.steps(1.0 / cfg.dt, cfg.gps.rate_hz, source="simulated")


class LogExport:
    """Writes each flight of the batches it is given as logs under ``directory``:
    ``flight_NNNN.ulg`` / ``.bin`` (NNNN: the flight id; ``name`` instead of ``flight``) and, for an
    attacked flight, ``flight_NNNN.attack.json``; the sensors logged under ``conditions``
    (checked against ``cfg``'s rates here; when they change anything, written to
    ``CONDITIONS_FILE`` in ``directory``). Call it with each ``BatchResult``
    (``simulate(on_batch=...)``)."""

    def __init__(self, cfg: SimConfig, directory: str | Path, formats: Iterable[str] = EXPORT_FORMATS,
                 header: LogHeader | None = None, name: str = "flight",
                 conditions: LogConditions | None = None) -> None:
        self.cfg = cfg
        self.name = name
        self.directory = Path(directory)
        self.formats = export_formats(formats)
        self.header = header or LogHeader(utc0=UTC0)
        self.conditions = conditions or LogConditions()
        check_conditions(cfg, self.conditions)
        self.written: list[Path] = []

    def __call__(self, r) -> None:
        self.directory.mkdir(parents=True, exist_ok=True)
        if self.conditions.active and not (self.directory / CONDITIONS_FILE).exists():
            self.written.append(write_json(self.directory / CONDITIONS_FILE, {
                **self.conditions.to_dict(), "seed": self.cfg.seed,
                "random": "each flight's quadformer.rng Stream.LOG generator (seed, flight id)"}))
        for i, fid in enumerate(np.asarray(r["flights"])):
            stem = f"{self.name}_{int(fid):04d}"
            log = flight_log(self.cfg, r, i, path=self.directory / stem)
            log, header = apply_conditions(log, self.conditions, self.header,
                                           flight_generator(self.cfg.seed, int(fid), Stream.LOG))
            for fmt in self.formats:
                self.written.append(WRITERS[fmt](log, self.directory / (stem + SUFFIX[fmt]), header))
            note = attack_note(r, i)
            if note is not None:
                self.written.append(write_json(self.directory / f"{stem}.attack.json", note))


def simulate_with_logs(cfg: SimConfig, out: str | Path, formats: Iterable[str], overwrite: bool = False,
                       progress: bool | Callable[[float], None] = False,
                       name: str = "flight", conditions: LogConditions | None = None
                       ) -> tuple[Dataset, Path, list[Path]]:
    """Simulate ``cfg`` and write the dataset to ``out`` with every flight's logs under
    ``out/logs`` (``LogExport``, the files named ``{name}_NNNN``, the sensors logged under
    ``conditions``); the dataset is the one ``simulate`` gives. The logs are
    written beside ``out`` first and moved in with the dataset, which appears at once.
    Returns (dataset, logs directory, files written)."""
    from quadformer.simulation import simulate

    out = Path(out)
    fmts = export_formats(formats)
    check_conditions(cfg, conditions or LogConditions())
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out} already exists (use --overwrite to replace it)")
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out.parent, prefix=f".{out.name}.logs.") as staging:
        export = LogExport(cfg, Path(staging) / "logs", fmts, name=name, conditions=conditions)
        ds = simulate(cfg, progress=progress, on_batch=export)
        write_dataset(ds, out, overwrite=overwrite, extra={"logs": export.directory})
    logs = out / "logs"
    return ds, logs, [logs / p.name for p in export.written]
