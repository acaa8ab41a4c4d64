"""Sensor noise estimated from clean flight logs, as simulator settings.

A detector trained in simulation expects the residue statistics of the simulated sensors; a
fleet whose GPS or IMU is quieter or noisier than the simulator's defaults shifts them. This
estimates, from logs without spoofing, the noise levels the simulator models, so that
``quadformer simulate --noise-from LOG`` produces data of the fleet's noise (and the replay
matched to that simulation has the filter tuning the data call for):

- GPS: the fixes against the autopilot's own estimate (which fuses them with the IMU). The
  step-to-step part of the difference is white noise (std of first differences / sqrt 2);
  what remains of its variance is slow, Gauss-Markov-like error. Velocity likewise.
- IMU: the step-to-step part of the specific force and body rate (std of first differences /
  sqrt 2) per sample, as a noise density at the log's IMU rate; vibration counts as noise.
- Barometer: its altitude against the autopilot's height, white and slow parts as for GPS.
- Magnetometer: the step-to-step part of the field.

Estimates below a floor (a simulator's sensor is never perfect) are raised to it. Every
estimate pools the samples of all logs given.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from quadformer.logs.flightlog import FlightLog, LogError

FLOORS = {"gps_pos_h": 0.05, "gps_pos_v": 0.05, "gps_vel": 0.02, "gps_gm": 0.0, "accel_density": 1e-3,
          "gyro_density": 1e-4, "baro_noise": 0.05, "baro_gm": 0.0, "mag_noise": 5e-4}


@dataclass(frozen=True)
class NoiseEstimate:
    gps_pos_h: float      # m, white horizontal position noise
    gps_pos_v: float      # m, white vertical position noise
    gps_vel: float        # m/s, white velocity noise
    gps_gm: float         # m, slow (Gauss-Markov) position error
    accel_density: float  # m/s^2/sqrt(Hz)
    gyro_density: float   # rad/s/sqrt(Hz)
    baro_noise: float     # m
    baro_gm: float        # m
    mag_noise: float      # gauss
    logs: int
    gps_fixes: int

    def sim_overrides(self) -> dict[str, Any]:
        """Nested ``SimConfig`` settings (``SimConfig.from_dict`` / ``--set`` keys)."""
        return {"gps": {"pos_std_h": self.gps_pos_h, "pos_std_v": self.gps_pos_v, "vel_std": self.gps_vel,
                        "gm_std": self.gps_gm},
                "imu": {"accel_noise_density": self.accel_density, "gyro_noise_density": self.gyro_density},
                "baro": {"noise_std": self.baro_noise, "gm_std": self.baro_gm},
                "mag": {"noise_std": self.mag_noise}}

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _white_and_slow(d: np.ndarray) -> tuple[float, float]:
    """(white std, slow std) of differences d (n, k) pooled over columns: the white part from
    first differences, the slow part from the variance left over."""
    d = d[np.isfinite(d).all(axis=1)]
    if len(d) < 3:
        return float("nan"), float("nan")
    white = float(np.sqrt(np.mean(np.diff(d, axis=0) ** 2) / 2))
    total = float(np.mean((d - d.mean(axis=0)) ** 2))
    return white, float(np.sqrt(max(total - white ** 2, 0.0)))


def _interp(t: np.ndarray, ref, cols) -> np.ndarray:
    return np.stack([np.interp(t, ref["t"].to_numpy(), ref[c].to_numpy()) for c in cols], axis=1)


def estimate_noise(logs: list[FlightLog]) -> NoiseEstimate:
    """Noise levels pooled over ``logs`` (clean flights), floored at ``FLOORS``."""
    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("h", "v", "vel", "acc", "gyro", "baro", "mag")}
    rates: list[float] = []
    fixes = 0
    for log in logs:
        g, e = log.gps, log.estimate
        if g is not None and e is not None and len(g) > 3 and len(e) > 1:
            d = g[["x", "y", "z"]].to_numpy() - _interp(g["t"].to_numpy(), e, ["x", "y", "z"])
            parts["h"].append(d[:, :2])
            parts["v"].append(d[:, 2:])
            dv = g[["vx", "vy", "vz"]].to_numpy() - _interp(g["t"].to_numpy(), e, ["vx", "vy", "vz"])
            parts["vel"].append(dv)
            fixes += len(g)
        if log.imu is not None and len(log.imu) > 3:
            imu = log.imu
            rates.append(1.0 / float(np.median(np.diff(imu["t"].to_numpy()))))
            parts["acc"].append(imu[["ax", "ay", "az"]].to_numpy())
            parts["gyro"].append(imu[["gx", "gy", "gz"]].to_numpy())
        if log.baro is not None and e is not None and len(log.baro) > 3:
            b = log.baro
            z = _interp(b["t"].to_numpy(), e, ["z"])[:, 0]
            parts["baro"].append((b["alt"].to_numpy() - z)[:, None])
        if log.mag is not None and len(log.mag) > 3:
            parts["mag"].append(log.mag[["mx", "my", "mz"]].to_numpy())
    if not fixes:
        raise LogError("noise: no log with both GPS fixes and the autopilot's position estimate; the GPS noise "
                       "cannot be estimated")

    def pooled(key: str) -> tuple[float, float]:
        """White and slow std pooled over logs (variances weighted by samples)."""
        ests = [(len(d), *_white_and_slow(d)) for d in parts[key] if len(d) >= 3]
        ests = [e for e in ests if np.isfinite(e[1])]
        if not ests:
            return float("nan"), float("nan")
        n = np.array([e[0] for e in ests], float)
        w = np.sqrt(np.sum(n * np.array([e[1] for e in ests]) ** 2) / n.sum())
        s = np.sqrt(np.sum(n * np.array([e[2] for e in ests]) ** 2) / n.sum())
        return float(w), float(s)

    h_w, h_s = pooled("h")
    v_w, _ = pooled("v")
    vel_w, _ = pooled("vel")
    acc_w, _ = pooled("acc")
    gyro_w, _ = pooled("gyro")
    baro_w, baro_s = pooled("baro")
    mag_w, _ = pooled("mag")
    rate = float(np.median(rates)) if rates else 100.0
    density = np.sqrt(rate / 2.0)              # per-sample std = density * sqrt(rate / 2)
    raw = {"gps_pos_h": h_w, "gps_pos_v": v_w, "gps_vel": vel_w, "gps_gm": h_s, "accel_density": acc_w / density,
           "gyro_density": gyro_w / density, "baro_noise": baro_w, "baro_gm": baro_s, "mag_noise": mag_w}
    out = {k: max(FLOORS[k], v) if np.isfinite(v) else FLOORS[k] for k, v in raw.items()}
    return NoiseEstimate(**{k: float(v) for k, v in out.items()}, logs=len(logs), gps_fixes=fixes)
