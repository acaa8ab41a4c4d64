"""The error-state EKF on its own, over recorded sensor streams.

The same ``predict`` / ``gps_update`` / ``vio_update`` and ``ResidueTracker`` as in the
closed loop, driven by timestamps: after each IMU sample, the VIO and then GPS samples
stamped at or before it are applied. Batched over flights that share timestamps (simulated
flights); a single real log is a batch of one.

Bad input gets a clear error: non-increasing or non-finite timestamps, non-finite samples,
gaps in the IMU stream longer than ``max_gap`` (the filter cannot propagate across them).
"""

from __future__ import annotations

import numpy as np
import torch

from quadformer.estimator.eskf import EKFState, NoiseModel, gps_update, predict, vio_update
from quadformer.estimator.residues import ResidueTracker


class StreamError(ValueError):
    """A recorded sensor stream the filter cannot process; the message names the stream."""


def _check(name: str, t: np.ndarray, x: torch.Tensor) -> None:
    t = np.asarray(t, dtype=float)
    if t.ndim != 1 or x.shape[1] != len(t):
        raise StreamError(f"{name}: {len(t)} timestamps for {x.shape[1]} samples")
    if not np.isfinite(t).all():
        raise StreamError(f"{name}: non-finite timestamp at index {int(np.argmin(np.isfinite(t)))}")
    if len(t) > 1 and np.any(np.diff(t) <= 0):
        i = int(np.argmax(np.diff(t) <= 0))
        raise StreamError(f"{name}: timestamps must increase (index {i + 1}: {t[i + 1]} after {t[i]})")
    bad = ~torch.isfinite(x).all(-1)
    if bad.any():
        b, i = (int(v) for v in torch.nonzero(bad)[0])
        raise StreamError(f"{name}: non-finite sample at index {i} (flight {b}, t = {t[i]})")


def run_ekf(ekf0: EKFState, nm: NoiseModel, dt: float, imu_t, imu: torch.Tensor, vio_t, vio: torch.Tensor,
            gps_t, gps: torch.Tensor, t0: float = 0.0, gps_rate_hz: float = 10.0, max_gap: float = 0.1
            ) -> dict[str, np.ndarray]:
    """Residues and estimates at every GPS sample.

    imu: (B, N, 6) specific force and body rate; vio: (B, M, 7) velocity and attitude
    quaternion (xyzw); gps: (B, K, 6) position and velocity; times in seconds, ``ekf0`` the
    filter state at ``t0``. Returns arrays (B, K, k) named like the dataset columns' groups.
    """
    for name, t, x in (("imu", imu_t, imu), ("vio", vio_t, vio), ("gps", gps_t, gps)):
        _check(name, t, x)
    imu_t, vio_t, gps_t = (np.asarray(v, dtype=float) for v in (imu_t, vio_t, gps_t))
    steps = np.diff(np.r_[t0, imu_t])
    if len(steps) and steps.max() > max_gap:
        i = int(np.argmax(steps))
        raise StreamError(f"imu: gap of {steps[i]:.3f} s before t = {imu_t[i]:.3f} s (more than {max_gap} s); "
                          f"split the log there")
    B, K = gps.shape[0], gps.shape[1]
    tracker = ResidueTracker(B, gps_rate_hz)
    out: dict[str, np.ndarray] = {}
    ekf = ekf0
    iv = ig = 0
    eps = 1e-9
    for i, t in enumerate(imu_t):
        h = dt if abs(steps[i] - dt) < eps else float(steps[i])
        ekf = predict(ekf, imu[:, i, 0:3], imu[:, i, 3:6], h, nm)
        while iv < len(vio_t) and vio_t[iv] <= t + eps:
            ekf, inn = vio_update(ekf, vio[:, iv, 0:3], vio[:, iv, 3:7], nm)
            tracker.on_vio(inn)
            iv += 1
        while ig < K and gps_t[ig] <= t + eps:
            ekf, inn = gps_update(ekf, gps[:, ig, 0:3], gps[:, ig, 3:6], nm)
            row = {"est_pos": ekf.p, "est_vel": ekf.v, **tracker.on_gps(inn)}
            for k, v in row.items():
                out.setdefault(k, np.zeros((B, K, v.shape[-1])))[:, ig] = v.numpy()
            ig += 1
    if ig < K:
        raise StreamError(f"gps: {K - ig} samples after the last IMU sample (t = {imu_t[-1] if len(imu_t) else t0})")
    return out
