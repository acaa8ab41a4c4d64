"""A flight log as rows of the flight table: residues two ways.

- ``ekf``: the project's own error-state EKF (``estimator.replay.run_ekf``, the same
  functions as in the closed loop) replayed over the log's IMU, GPS and, where the log has
  them and the sensor configuration asks for them, magnetometer, barometer and visual
  odometry. It produces the residue schema's columns, so every registered detector applies
  unchanged. Conventions, as in PX4 EKF2: the IMU is averaged down to at most
  ``imu_rate_hz`` (EKF2 predicts at 100 Hz), fixes are fused at most at ``gps_rate_hz`` (the
  detectors' windows count GPS steps; the simulator's GPS runs at 10 Hz), and each fix's
  noise is the larger of a floor and the receiver's own accuracy (eph, epv, speed accuracy).
  The filter starts at the first fix of a segment, from that fix, the autopilot's attitude
  (or the accelerometer's tilt) and the configured initial uncertainty.
- ``autopilot``: the autopilot's own logged GPS innovations, whitened by its logged
  variances, for logs whose raw sensors are missing or too sparse. PX4 and ArduPilot define
  an innovation as predicted minus measured; here, as everywhere in the project, it is
  measured minus predicted (the sign is flipped). Groups the log cannot provide (whitened
  innovations and NIS without logged variances, as in ArduPilot's XKF3; the correction
  integral; VIO, magnetometer and barometer residues) are absent, and ``missing_features``
  names them for a detector that needs them.

A spoof can be injected into the logged GPS stream before the ``ekf`` replay (``attack``):
open loop, the recorded vehicle does not react to it (it flew on its honest estimate).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from quadformer.estimator.schema import GROUPS, RESIDUES
from quadformer.logs.flightlog import FlightLog, LogError

RESIDUE_SOURCES = ("ekf", "autopilot")
SENSOR_NAMES = ("gps", "imu", "vio", "mag", "baro")

#: the autopilot residues: which schema groups each kind of logged innovation provides
AUTOPILOT_GROUPS = ("res_gps_r", "res_gps_w", "res_gps_s", "res_gps_nis")

#: leading autopilot innovations larger than this (m) are from before its GPS fusion started
INIT_INNOVATION_M = 1000.0

#: extra per-fix columns kept from the log for reports (not detector inputs)
RECEIVER = {"fix_type": "gps_fix_type", "satellites": "gps_satellites", "eph": "gps_eph",
            "epv": "gps_epv", "speed_acc": "gps_speed_acc", "jamming": "gps_jamming",
            "spoofing": "gps_spoofing"}


@dataclass(frozen=True)
class ReplayConfig:
    """How a log is replayed through the filter. Noise defaults are PX4 EKF2's parameter
    defaults (EKF2_ACC_NOISE, EKF2_GYR_NOISE, EKF2_ACC_B_NOISE, EKF2_GYR_B_NOISE,
    EKF2_GPS_P_NOISE, EKF2_GPS_V_NOISE, EKF2_BARO_NOISE, EKF2_HEAD_NOISE); ``matching`` takes
    a simulation's instead. IMU noise is per filter step at ``imu_rate_hz`` and is scaled to
    keep its density when a log's IMU is slower."""
    sensors: str | None = None      # e.g. "gps+imu+mag+baro"; None: every sensor the log has
    imu_rate_hz: float = 100.0      # Hz, IMU averaged down to at most this rate
    gps_rate_hz: float = 10.0       # Hz, at most this many fixes fused per second
    accel_noise: float = 0.35       # m/s^2, accelerometer noise per filter step
    gyro_noise: float = 0.015       # rad/s, gyro noise per filter step
    accel_bias_walk: float = 3e-3   # m/s^3, accelerometer bias random walk
    gyro_bias_walk: float = 1e-3    # rad/s^2, gyro bias random walk
    gps_pos_noise: float = 0.5      # m, floor of the horizontal position std (eph used when larger)
    gps_alt_noise: float = 0.75     # m, floor of the vertical position std (epv used when larger)
    gps_vel_noise: float = 0.3      # m/s, floor of the velocity std (speed accuracy used when larger)
    baro_noise: float = 3.5         # m, barometric height std
    heading_noise: float = 0.3      # rad, magnetometer heading std
    vio_vel_noise: float = 0.1      # m/s, visual odometry velocity std
    vio_att_noise_deg: float = 2.0  # deg, visual odometry attitude std
    init_vel_std: float = 0.5       # m/s, initial velocity uncertainty
    init_att_std_deg: float = 5.0   # deg, initial roll/pitch/yaw uncertainty (given an attitude)
    init_yaw_std_deg: float = 60.0  # deg, initial yaw uncertainty without the autopilot's attitude
    accel_bias_std: float = 0.2     # m/s^2, initial accelerometer bias uncertainty
    gyro_bias_std: float = 0.01     # rad/s, initial gyro bias uncertainty
    receiver_accuracy: bool = True  # use the receiver's eph/epv/speed accuracy when above the floors
    max_gap_s: float = 0.5          # s, the longest IMU gap the filter propagates across
    min_segment_s: float = 3.0      # s of GPS a segment needs to be replayed

    @classmethod
    def matching(cls, sim: dict[str, Any], **overrides: Any) -> "ReplayConfig":
        """The filter tuning of simulated data (a dataset's resolved ``SimConfig`` as a dict):
        the residues of a replayed log then have the scale of the residues a detector was
        fit on. The receiver's own accuracies are not used (the simulated filter has none)."""
        from quadformer.config import SimConfig
        from quadformer.estimator.eskf import noise_model

        cfg = SimConfig.from_dict(sim)
        nm = noise_model(cfg.imu, cfg.gps, cfg.vio, cfg.ekf, 1.0 / cfg.dt, cfg.mag, cfg.baro)
        g = nm.gps_std.tolist()
        v = nm.vio_std.tolist()
        values = dict(
            sensors=None, imu_rate_hz=1.0 / cfg.dt, gps_rate_hz=cfg.gps.rate_hz,
            accel_noise=nm.accel_std, gyro_noise=nm.gyro_std,
            accel_bias_walk=nm.accel_walk / cfg.dt, gyro_bias_walk=nm.gyro_walk / cfg.dt,
            gps_pos_noise=g[0], gps_alt_noise=g[2], gps_vel_noise=g[3],
            baro_noise=float(nm.baro_std[0]), heading_noise=float(nm.mag_std[0]),
            vio_vel_noise=v[0], vio_att_noise_deg=float(np.rad2deg(v[3])),
            init_vel_std=cfg.ekf.init_vel_std, init_att_std_deg=cfg.ekf.init_att_std_deg,
            accel_bias_std=cfg.imu.accel_bias_std, gyro_bias_std=cfg.imu.gyro_bias_std,
            receiver_accuracy=False)
        values.update(overrides)
        return cls(**values)

    def __post_init__(self) -> None:
        for name in ("imu_rate_hz", "gps_rate_hz", "accel_noise", "gyro_noise", "gps_pos_noise",
                     "gps_alt_noise", "gps_vel_noise", "baro_noise", "heading_noise", "vio_vel_noise",
                     "vio_att_noise_deg", "init_vel_std", "init_att_std_deg", "init_yaw_std_deg",
                     "max_gap_s", "min_segment_s", "accel_bias_std", "gyro_bias_std"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"replay.{name} must be a positive number, got {v!r}")
        for name in ("accel_bias_walk", "gyro_bias_walk"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"replay.{name} must be a non-negative number, got {v!r}")
        if self.sensors is not None:
            parts = set(self.sensors.split("+"))
            unknown = parts - set(SENSOR_NAMES)
            if unknown or not {"gps", "imu"} <= parts:
                raise ValueError(f"replay.sensors: {self.sensors!r} must join gps, imu and any of vio, mag, "
                                 f"baro with '+' (unknown: {', '.join(sorted(unknown)) or 'none'})")


@dataclass
class LogFlight:
    """The rows of one replayed segment of a log (``flight_id`` = segment index)."""
    segment: int
    rows: pd.DataFrame
    sensors: str
    notes: list[str] = field(default_factory=list)


def missing_features(features: list[str], columns) -> list[str]:
    """The detector inputs ``features`` absent from ``columns``, as schema group names."""
    cols = set(columns)
    groups = []
    for f in features:
        if f in cols:
            continue
        g = next((g.name for g in GROUPS.values() if f in g.columns), f)
        if g not in groups:
            groups.append(g)
    return groups


# --------------------------------------------------------------------------- helpers
def _resample_imu(t: np.ndarray, v: np.ndarray, rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """Average consecutive samples into bins of 1/rate s (a sample's time: the last in its bin)."""
    if len(t) < 2 or np.median(np.diff(t)) >= 1.0 / rate_hz * 0.999:
        return t, v
    bins = np.floor((t - t[0]) * rate_hz + 1e-9).astype(np.int64)
    edges = np.r_[np.flatnonzero(np.diff(bins)) + 1, len(t)]
    starts = np.r_[0, edges[:-1]]
    sums = np.add.reduceat(v, starts, axis=0)
    return t[edges - 1], sums / (edges - starts)[:, None]


def _decimate(t: np.ndarray, rate_hz: float) -> np.ndarray:
    """Indices of fixes at least about 1/rate s apart (the first one kept)."""
    keep, last = [], -np.inf
    min_dt = 0.9 / rate_hz
    for i, ti in enumerate(t):
        if ti - last >= min_dt:
            keep.append(i)
            last = ti
    return np.asarray(keep, dtype=np.int64)


def _interp(t_new: np.ndarray, t: np.ndarray, v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    if v.ndim == 1:
        return np.interp(t_new, t, v)
    return np.stack([np.interp(t_new, t, v[:, i]) for i in range(v.shape[1])], axis=1)


def _quat_at(t0: float, att: pd.DataFrame | None) -> np.ndarray | None:
    if att is None or len(att) == 0:
        return None
    i = int(np.clip(np.searchsorted(att["t"].to_numpy(), t0), 0, len(att) - 1))
    q = att[["qx", "qy", "qz", "qw"]].to_numpy()[i]
    return q / np.linalg.norm(q)


def _tilt_quat(acc: np.ndarray) -> np.ndarray:
    """Roll and pitch from the mean specific force of a (near) static start, yaw 0 (xyzw)."""
    ax, ay, az = acc
    roll, pitch = math.atan2(ay, az), math.atan2(-ax, math.hypot(ay, az))
    cr, sr, cp, sp = math.cos(roll / 2), math.sin(roll / 2), math.cos(pitch / 2), math.sin(pitch / 2)
    return np.array([sr * cp, cr * sp, -sr * sp, cr * cp])


def _sensors_of(log: FlightLog, config: ReplayConfig) -> str:
    have = ["gps", "imu"]
    if log.odometry is not None:
        have.append("vio")
    if log.mag is not None:
        have.append("mag")
    if log.baro is not None:
        have.append("baro")
    if config.sensors is None:
        return "+".join(have)
    want = config.sensors.split("+")
    lacking = [s for s in want if s not in have]
    if lacking:
        raise LogError(f"{log.path}: the sensor configuration {config.sensors!r} needs "
                       f"{', '.join(lacking)}, which this log lacks (it has {'+'.join(have)}); "
                       f"choose --sensors {'+'.join(have)} or a subset")
    return "+".join(s for s in SENSOR_NAMES if s in want)


def _base_rows(seg: int, t: np.ndarray, gps: pd.DataFrame, log: FlightLog) -> dict[str, np.ndarray]:
    """Keys, labels (clean), the fixes, the autopilot's estimate and the receiver at times t."""
    n = len(t)
    cols: dict[str, Any] = {"flight_id": np.full(n, seg, dtype=np.int32), "t": t,
                            "label": np.zeros(n, dtype=np.int8), "attack_type": np.full(n, "none", dtype=object)}
    gt = gps["t"].to_numpy()
    idx = np.clip(np.searchsorted(gt, t - 1e-9), 0, len(gt) - 1)
    for a in "xyz":
        cols[f"gps_pos_{a}"] = gps[a].to_numpy()[idx]
        cols[f"gps_vel_{a}"] = gps[f"v{a}"].to_numpy()[idx]
    for src, dst in RECEIVER.items():
        cols[dst] = gps[src].to_numpy()[idx]
    if log.estimate is not None and len(log.estimate) > 1:
        e = log.estimate
        pos = _interp(t, e["t"].to_numpy(), e[["x", "y", "z"]].to_numpy())
        for i, a in enumerate("xyz"):
            cols[f"ap_pos_{a}"] = pos[:, i]
    if log.truth is not None and len(log.truth) > 1:
        tr = log.truth
        pos = _interp(t, tr["t"].to_numpy(), tr[["x", "y", "z"]].to_numpy())
        vel = _interp(t, tr["t"].to_numpy(), tr[["vx", "vy", "vz"]].to_numpy())
        for i, a in enumerate("xyz"):
            cols[f"true_pos_{a}"] = pos[:, i]
            cols[f"true_vel_{a}"] = vel[:, i]
    return cols


# --------------------------------------------------------------------------- autopilot
def autopilot_rows(log: FlightLog, seg: int = 0) -> pd.DataFrame:
    """Rows at the autopilot's innovation samples of segment ``seg``."""
    part = log.segment(seg) if len(log.segments) > 1 else log
    inn = part.innovations
    if inn is None or len(inn) == 0:
        raise LogError(f"{log.path}: no GPS innovations logged (PX4 estimator_innovations, ArduPilot "
                       "XKF3); use --residues ekf to replay the project's filter over the raw sensors")
    if part.gps is None or len(part.gps) == 0:
        raise LogError(f"{log.path}: no GPS fixes in segment {seg}")
    # the autopilot reports innovations before it fuses any fix (PX4: against an unset fix, some
    # thousand km off): keep the samples from the first fix on, and from the first innovation
    # within 1 km (the autopilot has initialised its GPS fusion) on
    first_fix = float(part.gps["t"].iloc[0])
    inn = inn[(inn["t"].to_numpy() >= first_fix)
              & np.isfinite(inn[["pos_x", "pos_y", "vel_x", "vel_y"]].to_numpy()).all(axis=1)]
    sane = np.abs(np.nan_to_num(inn[["pos_x", "pos_y", "pos_z"]].to_numpy())).max(axis=1) < INIT_INNOVATION_M
    if not sane.any():
        raise LogError(f"{log.path}: segment {seg}: the autopilot never fused GPS (no innovation within "
                       f"{INIT_INNOVATION_M:g} m after the first fix)")
    inn = inn.iloc[int(np.argmax(sane)):]
    t = inn["t"].to_numpy()
    cols = _base_rows(seg, t, part.gps, part)
    r = -np.nan_to_num(inn[["pos_x", "pos_y", "pos_z", "vel_x", "vel_y", "vel_z"]].to_numpy())  # measured - predicted
    var = inn[["var_pos_x", "var_pos_y", "var_pos_z", "var_vel_x", "var_vel_y", "var_vel_z"]].to_numpy()
    names = GROUPS["res_gps_r"].axes
    for i, a in enumerate(names):
        cols[f"res_gps_r_{a}"] = r[:, i]
    if np.isfinite(var).any():
        # a component the autopilot did not fuse (no positive variance, e.g. PX4's vertical
        # position when the barometer is the height source) contributes zero
        fused = np.isfinite(var) & (var > 0)
        s = np.sqrt(np.where(fused, var, 0.0))
        w = np.where(fused, r / np.where(fused, s, 1.0), 0.0)
        for i, a in enumerate(names):
            cols[f"res_gps_s_{a}"] = s[:, i]
            cols[f"res_gps_w_{a}"] = w[:, i]
        cols["res_gps_nis"] = (w * w).sum(axis=1)
    return pd.DataFrame(cols)


# --------------------------------------------------------------------------- ekf
def ekf_rows(log: FlightLog, seg: int = 0, config: ReplayConfig = ReplayConfig(),
             attack=None) -> LogFlight:
    """Replay the project's filter over segment ``seg`` of ``log``. ``attack``: an
    ``attacks.AttackBatch`` of one flight whose times count from the segment's first fix."""
    return ekf_flights(log, seg, config, [attack])[0]


def ekf_flights(log: FlightLog, seg: int = 0, config: ReplayConfig = ReplayConfig(),
                attacks: list = (None,)) -> list[LogFlight]:
    """``ekf_rows`` for several injections into the same segment (None: none), replayed
    together as one batch of flights sharing the log's timestamps."""
    import torch

    from quadformer.estimator.eskf import init_state
    from quadformer.estimator.replay import StreamError, run_ekf

    part = log.segment(seg) if len(log.segments) > 1 else log
    sensors = _sensors_of(part, config)
    notes: list[str] = []
    imu, gps = part.imu, part.gps
    if imu is None or gps is None:
        raise LogError(f"{log.path}: segment {seg} has no {'IMU' if imu is None else 'GPS'} samples; the ekf "
                       "replay needs both (use --residues autopilot for the autopilot's innovations)")
    gps = gps[np.isfinite(gps[["x", "y", "z"]].to_numpy()).all(axis=1)].reset_index(drop=True)
    keep = _decimate(gps["t"].to_numpy(), config.gps_rate_hz)
    if len(keep) < len(gps):
        notes.append(f"gps: {len(gps)} fixes decimated to {len(keep)} (at most {config.gps_rate_hz:g} Hz)")
    gps = gps.iloc[keep].reset_index(drop=True)
    span = gps["t"].iloc[-1] - gps["t"].iloc[0] if len(gps) else 0.0
    if len(gps) < 3 or span < config.min_segment_s:
        raise LogError(f"{log.path}: segment {seg} holds {span:.1f} s of GPS ({len(gps)} fixes); the replay needs "
                       f"at least {config.min_segment_s:g} s (--min-segment)")
    gt = gps["t"].to_numpy()
    pos = gps[["x", "y", "z"]].to_numpy()
    vel = gps[["vx", "vy", "vz"]].to_numpy()
    if not np.isfinite(vel).all():
        bad = ~np.isfinite(vel).all(axis=1)
        vel[bad] = np.gradient(pos, gt, axis=0)[bad]
        notes.append(f"gps: {int(bad.sum())} fixes without velocity; velocity from the derivative of position")
    acc = (lambda c: np.nan_to_num(gps[c].to_numpy(), nan=0.0)) if config.receiver_accuracy \
        else (lambda c: np.zeros(len(gps)))
    std = np.column_stack([
        np.fmax(acc("eph"), config.gps_pos_noise).repeat(2).reshape(-1, 2),
        np.fmax(acc("epv"), config.gps_alt_noise),
        np.fmax(acc("speed_acc"), config.gps_vel_noise).repeat(3).reshape(-1, 3),
    ])
    t0 = float(gt[0])
    fixes = []              # per flight: spoofed positions, velocities, labels, offsets
    for attack in attacks:
        if attack is None:
            fixes.append((pos, vel, np.zeros(len(gt), dtype=bool), np.zeros((len(gt), 3))))
        else:
            fixes.append(_inject(attack, gt - t0, pos, vel, config.gps_rate_hz))
    B = len(fixes)

    it = imu["t"].to_numpy()
    iv = imu[["ax", "ay", "az", "gx", "gy", "gz"]].to_numpy()
    it, iv = _resample_imu(it, iv, config.imu_rate_hz)
    after = it > t0
    if after.sum() < 2:
        raise LogError(f"{log.path}: segment {seg} has no IMU samples after its first fix")
    q0 = _quat_at(t0, part.attitude)
    yaw_std = config.init_att_std_deg
    if q0 is None:
        near = (it >= t0 - 0.5) & (it <= t0 + 0.5)
        q0 = _tilt_quat(iv[near, :3].mean(axis=0) if near.any() else iv[after][0, :3])
        yaw_std = config.init_yaw_std_deg
        notes.append("attitude: none logged; initial roll and pitch from the accelerometer, yaw 0 "
                     f"(std {yaw_std:g} deg)")
    att = np.deg2rad([config.init_att_std_deg, config.init_att_std_deg, yaw_std])
    std0 = np.r_[std[0, :3], [config.init_vel_std] * 3, att, [config.accel_bias_std] * 3,
                 [config.gyro_bias_std] * 3]
    T = lambda x: torch.as_tensor(np.array(x, dtype=float))[None].expand(B, *np.shape(x))   # noqa: E731  shared
    ekf0 = init_state(torch.as_tensor(np.stack([f[0][0] for f in fixes])),
                      torch.as_tensor(np.stack([f[1][0] for f in fixes])), T(q0), torch.zeros(B, 3),
                      torch.zeros(B, 3), torch.diag(torch.as_tensor(std0 ** 2)).expand(B, 15, 15))
    dt = float(np.median(np.diff(it)))
    mag_field = None
    kw: dict[str, Any] = {}
    if "vio" in sensors:
        o = part.odometry
        ot = o["t"].to_numpy()
        sel = ot > t0
        kw.update(vio_t=ot[sel], vio=T(o[["vx", "vy", "vz", "qx", "qy", "qz", "qw"]].to_numpy()[sel]))
    if "mag" in sensors:
        m = part.mag
        mt = m["t"].to_numpy()
        mv = m[["mx", "my", "mz"]].to_numpy()
        sel = mt > t0
        # the local field in the world frame, from the first second of samples and the initial
        # attitude: headings are measured against it (declination and inclination included)
        first = (mt >= t0 - 0.5) & (mt <= t0 + 0.5)
        mag_field = _rotate(q0, (mv[first] if first.any() else mv[sel][:1]).mean(axis=0))
        kw.update(mag_t=mt[sel], mag=T(mv[sel]))
    if "baro" in sensors:
        b = part.baro
        bt = b["t"].to_numpy()
        alt = b["alt"].to_numpy()
        ref = np.interp(t0, bt, alt)                                   # baro height relative to the first fix
        sel = bt > t0
        kw.update(baro_t=bt[sel], baro=T((alt[sel] - ref + pos[0, 2])[:, None]))
    nm = _noise_model(config, dt, mag_field)
    try:
        gps_b = torch.as_tensor(np.stack([np.c_[f[0], f[1]][1:] for f in fixes]))
        out = run_ekf(ekf0, nm, dt, it[after], T(iv[after]), gt[1:], gps_b,
                      gps_std=T(std[1:]), t0=t0, gps_rate_hz=config.gps_rate_hz, max_gap=config.max_gap_s, **kw)
    except StreamError as e:
        raise LogError(f"{log.path}: segment {seg}: {e}") from None
    base = _base_rows(seg, gt[1:], gps.iloc[1:].reset_index(drop=True), part)
    flights = []
    for b, (attack, (p_b, v_b, label, d_pos)) in enumerate(zip(attacks, fixes)):
        rows = dict(base)
        for a_i, a in enumerate("xyz"):          # the fixes as fused (spoofed when injected)
            rows[f"gps_pos_{a}"] = p_b[1:, a_i]
            rows[f"gps_vel_{a}"] = v_b[1:, a_i]
            rows[f"atk_d_{a}"] = d_pos[1:, a_i]
        rows["label"] = label[1:].astype(np.int8)
        rows["attack_type"] = np.where(label[1:], attack.kind if attack is not None else "none", "none").astype(object)
        for name, val in out.items():
            for i, c in enumerate(GROUPS[name].columns):
                rows[c] = val[b, :, i]
        flights.append(LogFlight(seg, pd.DataFrame(rows), sensors, list(notes)))
    return flights


def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """v (body) rotated by unit quaternion q (xyzw, body to world)."""
    x, y, z, w = q
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    return R @ v


def _noise_model(config: ReplayConfig, dt: float, mag_field: np.ndarray | None):
    """The filter's noise for a log whose IMU steps are dt seconds: the configured per-step
    noise at ``imu_rate_hz``, scaled to the same density at dt."""
    import torch

    from quadformer.estimator.eskf import NoiseModel

    f64 = lambda v: torch.tensor(v, dtype=torch.float64)   # noqa: E731
    c = config
    density = math.sqrt(1.0 / (c.imu_rate_hz * dt))      # per-step std ~ 1/sqrt(dt)
    return NoiseModel(
        accel_std=c.accel_noise * density, gyro_std=c.gyro_noise * density,
        accel_walk=c.accel_bias_walk * dt, gyro_walk=c.gyro_bias_walk * dt,
        gps_std=f64([c.gps_pos_noise, c.gps_pos_noise, c.gps_alt_noise] + [c.gps_vel_noise] * 3),
        vio_std=f64([c.vio_vel_noise] * 3 + [np.deg2rad(c.vio_att_noise_deg)] * 3),
        mag_std=f64([c.heading_noise]), baro_std=f64([c.baro_noise]),
        mag_field=None if mag_field is None else f64(mag_field))


def _inject(attack, tau: np.ndarray, pos: np.ndarray, vel: np.ndarray, rate_hz: float):
    """The spoofed fixes: ``attack`` (one flight) applied at each fix time tau (s from the
    segment's first fix), on the logged fixes."""
    import torch

    n = len(tau)
    history = torch.as_tensor(np.c_[pos, vel])[None]
    out_p, out_v = pos.copy(), vel.copy()
    label = np.zeros(n, dtype=bool)
    d_pos = np.zeros((n, 3))
    for j in range(n):
        p, v, active, d, _ = attack.apply(float(tau[j]), j, torch.as_tensor(pos[j:j + 1]),
                                          torch.as_tensor(vel[j:j + 1]), history, rate_hz)
        out_p[j], out_v[j] = p[0].numpy(), v[0].numpy()
        label[j], d_pos[j] = bool(active[0]), d[0]
    return out_p, out_v, label, d_pos


def residue_columns(rows: pd.DataFrame) -> list[str]:
    return [c for g in RESIDUES for c in g.columns if c in rows.columns]
