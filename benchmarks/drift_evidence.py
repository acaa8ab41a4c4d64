"""What a consistent drift leaves in a real log without a camera, measured on its clean flight.

A drift whose position and velocity agree, switched on at once, shows against the IMU as one
velocity step: the filter absorbs it, and after it the fixes and the IMU agree again. This
measures, on each clean log given (default: the clean ArduCopter logs of the real-flights set in
``../shared``; the repository holds no such log), the evidence there is and how sharp it can be:

- the step: one GPS interval's velocity change against the IMU's (``logs.noise.detection_floor``):
  its robust std, its largest value in the air in robust stds, the floor at 1 false alarm per
  in-air hour with a Gaussian of that std and with the log's own tails (a fitted Student-t);
- the receiver's own smoothing: the same residual with the IMU's velocity passed through a
  first-order lag of time constant ``tau`` before it is differenced (a receiver's velocity
  filter), at the ``tau`` in ``TAUS`` and the latency in ``LATENCIES`` that make it least spread:
  the robust std and the largest residual (m/s) that a sharper model of the receiver would give;
- rotor drag, the one evidence that persists after the step: the body-frame horizontal specific
  force of a multirotor is its drag, -mu (body velocity - wind); fitted over the flight (mu, a
  constant wind, an accelerometer bias), the residual's std averaged over 5 s and the shift 1 m/s
  of false velocity makes in it (mu x 1 m/s), as a signal-to-noise ratio at 5 s.

    python benchmarks/drift_evidence.py                     # the six clean ArduCopter logs
    python benchmarks/drift_evidence.py LOG [LOG ...]

The last line printed is one JSON object, one entry per log.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from quadformer.estimator.latency import robust_std
from quadformer.logs.receiver_clock import imu_velocity

REAL = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "real-flights"
CLEAN = ("BeastAyyG_sample.bin", "erlerobot_pxf_copter_10-11-2014_105.BIN", "erlerobot_pxf_copter_8-10-2014_11.BIN",
         "joeydouglas_2014-10-18_20-04-24.bin", "joeydouglas_2014-10-18_20-44-05.bin",
         "joeydouglas_2014-10-18_21-19-07.bin")
TAUS = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.7, 1.0)      # s, the receiver's velocity lag
LATENCIES = (0.0, 0.1, 0.2, 0.3, 0.4)               # s, the receiver's latency
DRAG_AVERAGE_S = 5.0
DRAG_MIN_CORR = 0.3     # the body-x force's correlation with the body-x velocity below which drag is unread


def lagged(ti: np.ndarray, v: np.ndarray, tau: float) -> np.ndarray:
    """``v`` through a first-order lag of time constant ``tau`` (exact for a piecewise constant input)."""
    if tau <= 0:
        return v
    out = np.empty_like(v)
    out[0] = v[0]
    a = 1.0 - np.exp(-np.diff(ti, prepend=ti[0]) / tau)
    for i in range(1, len(v)):
        out[i] = out[i - 1] + a[i] * (v[i] - out[i - 1])
    return out


def intervals(t: np.ndarray, air: np.ndarray, ti: np.ndarray) -> np.ndarray:
    dt = np.diff(t)
    step = float(np.median(dt))
    return (air[1:] & air[:-1] & (dt > 0) & (dt <= 1.5 * step) & (t[:-1] - max(LATENCIES) >= ti[0])
            & (t[1:] <= ti[-1]))


def receiver_lag(log, air: np.ndarray) -> dict:
    t = log.gps["t"].to_numpy(dtype=float)
    v = log.gps[["vx", "vy"]].to_numpy(dtype=float)
    _, _, ti, vi = imu_velocity(log)
    ok = intervals(t, air, ti) & np.isfinite(v).all(axis=1)[1:] & np.isfinite(v).all(axis=1)[:-1]
    dv = np.diff(v, axis=0)[ok]
    best: dict[float, tuple[float, float, float]] = {}
    for tau in TAUS:
        vl = lagged(ti, vi, tau)
        for lat in LATENCIES:
            at = np.stack([np.interp(t - lat, ti, vl[:, k]) for k in range(2)], axis=1)
            e = dv - np.diff(at, axis=0)[ok]
            s = robust_std(e)
            if tau not in best or s < best[tau][0]:
                best[tau] = (s, lat, float(np.linalg.norm(e, axis=1).max()))
    tau = min(best, key=lambda k: best[k][0])
    return {"intervals": int(ok.sum()),
            "no_lag": {"std": best[0.0][0], "latency_s": best[0.0][1], "largest": best[0.0][2]},
            "lag": {"tau_s": tau, "std": best[tau][0], "latency_s": best[tau][1], "largest": best[tau][2]}}


def drag(log, air: np.ndarray) -> dict | None:
    """Rotor drag fitted over the flight in the air, per GPS interval: the IMU's mean body-frame
    horizontal specific force f = -mu R_bw (v - w) + b (R_bw: world to body through the attitude at
    the interval's middle; v the fixes' mean velocity; w a constant wind; b a bias), by least
    squares in (mu, mu w, b)."""
    from quadformer.geometry.frames import quat_rotate

    t = log.gps["t"].to_numpy(dtype=float)
    v = log.gps[["vx", "vy", "vz"]].to_numpy(dtype=float)
    ti = log.imu["t"].to_numpy(dtype=float)
    f = log.imu[["ax", "ay"]].to_numpy(dtype=float)
    cum = np.concatenate([[np.zeros(2)], np.cumsum(0.5 * (f[1:] + f[:-1]) * np.diff(ti)[:, None], axis=0)])
    ok = intervals(t, air, ti) & np.isfinite(v).all(axis=1)[1:] & np.isfinite(v).all(axis=1)[:-1]
    if ok.sum() < 100:
        return None
    k = np.flatnonzero(ok)
    t0, t1 = t[k], t[k + 1]
    fb = np.stack([(np.interp(t1, ti, cum[:, a]) - np.interp(t0, ti, cum[:, a])) / (t1 - t0) for a in range(2)], 1)
    ta = log.attitude["t"].to_numpy(dtype=float)
    q = log.attitude[["qx", "qy", "qz", "qw"]].to_numpy(dtype=float)
    qm = q[np.clip(np.searchsorted(ta, 0.5 * (t0 + t1)), 0, len(ta) - 1)]
    qinv = qm * np.array([-1.0, -1.0, -1.0, 1.0])
    vb = quat_rotate(qinv, 0.5 * (v[k] + v[k + 1]))
    ex = quat_rotate(qinv, np.tile([1.0, 0.0, 0.0], (len(k), 1)))
    ey = quat_rotate(qinv, np.tile([0.0, 1.0, 0.0], (len(k), 1)))
    rows, y = [], []
    for a in range(2):
        rows.append(np.stack([-vb[:, a], ex[:, a], ey[:, a], np.full(len(k), a == 0), np.full(len(k), a == 1)], 1))
        y.append(fb[:, a])
    A, y = np.vstack(rows).astype(float), np.concatenate(y)
    p, *_ = np.linalg.lstsq(A, y, rcond=None)
    r = (y - A @ p).reshape(2, -1).T
    n = max(1, int(round(DRAG_AVERAGE_S / float(np.median(t1 - t0)))))
    avg = np.stack([np.convolve(r[:, a], np.ones(n) / n, mode="valid") for a in range(2)], 1)
    s5 = robust_std(avg)
    mu, corr = float(p[0]), float(np.corrcoef(fb[:, 0], vb[:, 0])[0, 1])
    # drag opposes the velocity: a fit without that sign (a hover, a vibrating airframe) has no drag to read
    seen = mu > 0 and corr < -DRAG_MIN_CORR
    return {"mu_per_s": mu, "corr_x": corr, "residual_std": robust_std(r), "residual_std_5s": s5,
            "snr_1ms_5s": mu / s5 if seen and s5 > 0 else math.nan,
            **({} if seen else {"note": "no drag to read: the force does not oppose the velocity"})}


def main() -> None:
    from quadformer.logs import read_log
    from quadformer.logs.noise import detection_floor
    from quadformer.logs.replay import in_air

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("logs", nargs="*", type=Path, default=[REAL / n for n in CLEAN])
    args = ap.parse_args()
    out = {}
    for path in args.logs:
        log = read_log(path)
        if log.gps is None or log.imu is None or log.attitude is None:
            out[path.name] = {"reason": "no GPS, IMU and attitude"}
            continue
        air = in_air(log, log.gps["t"].to_numpy()) > 0.5
        floor = detection_floor(log, air)
        entry = {"floor": None if floor is None else floor.to_dict(), "receiver": receiver_lag(log, air),
                 "drag": drag(log, air)}
        out[path.name] = entry
        rl, dr = entry["receiver"], entry["drag"]
        print(f"{path.name}: step std {rl['no_lag']['std']:.3f} m/s, largest {rl['no_lag']['largest']:.2f}; with a "
              f"{rl['lag']['tau_s']:.1f} s receiver lag {rl['lag']['std']:.3f}, largest {rl['lag']['largest']:.2f}; "
              + ("" if floor is None else f"floor {floor.drift_ms:.2f} m/s, with its tails {floor.drift_tail_ms:.2f}; ")
              + ("" if dr is None else f"drag mu {dr['mu_per_s']:.2f}/s, 1 m/s at 5 s: {dr['snr_1ms_5s']:.1f} std "
                                        f"{dr.get('note', '')}"))
    print(json.dumps(out, default=float))


if __name__ == "__main__":
    main()
