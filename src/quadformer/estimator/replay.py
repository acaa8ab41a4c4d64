"""The error-state EKF on its own, over recorded sensor streams.

The same ``predict``, updates and ``ResidueTracker`` as in the closed loop, driven by
timestamps through ``estimator.online.OnlineFilter`` (which a live link drives sample by
sample): after each IMU sample, the samples stamped at or before it are applied, in the
order VIO, magnetometer, barometer, then GPS. The aiding sensors are optional: the residue
groups follow the streams given. Batched over flights that share timestamps (simulated
flights); a single real log is a batch of one.

Bad input gets a clear error: non-increasing or non-finite timestamps, non-finite samples,
samples of the wrong width, gaps in the IMU stream longer than ``max_gap`` (the filter
cannot propagate across them).
"""

from __future__ import annotations

import numpy as np
import torch

from quadformer.estimator.eskf import EKFState, NoiseModel
from quadformer.estimator.online_filter import OnlineFilter, StreamError

# values per sample of each stream, and what they are
WIDTHS = {"imu": (6, "specific force and body rate"), "gps": (6, "position and velocity"),
          "vio": (7, "velocity and attitude quaternion"), "mag": (3, "body-frame field"), "baro": (1, "height"),
          "gps_std": (6, "position and velocity std")}


def _check(name: str, t: np.ndarray, x: torch.Tensor, flights: int) -> None:
    t = np.asarray(t, dtype=float)
    if t.ndim != 1 or x.shape[1] != len(t):
        raise StreamError(f"{name}: {len(t)} timestamps for {x.shape[1]} samples")
    _check_samples(name, t, x, flights)
    if not np.isfinite(t).all():
        raise StreamError(f"{name}: non-finite timestamp at index {int(np.argmin(np.isfinite(t)))}")
    if len(t) > 1 and np.any(np.diff(t) <= 0):
        i = int(np.argmax(np.diff(t) <= 0))
        raise StreamError(f"{name}: timestamps must increase (index {i + 1}: {t[i + 1]} after {t[i]})")
    bad = ~torch.isfinite(x).all(-1)
    if bad.any():
        b, i = (int(v) for v in torch.nonzero(bad)[0])
        raise StreamError(f"{name}: non-finite sample at index {i} (flight {b}, t = {t[i]})")


def _check_samples(name: str, t: np.ndarray, x: torch.Tensor, flights: int) -> None:
    width, what = WIDTHS[name]
    if x.dim() != 3 or x.shape[0] != flights or x.shape[2] != width:
        raise StreamError(f"{name}: samples shaped {tuple(x.shape)}, expected ({flights}, {len(t)}, {width}) "
                          f"(flights, samples, {what})")


def run_ekf(ekf0: EKFState, nm: NoiseModel, dt: float, imu_t, imu: torch.Tensor, gps_t, gps: torch.Tensor, *,
            vio_t=None, vio: torch.Tensor | None = None, mag_t=None, mag: torch.Tensor | None = None,
            baro_t=None, baro: torch.Tensor | None = None, gps_std: torch.Tensor | None = None,
            t0: float = 0.0, gps_rate_hz: float = 10.0, max_gap: float = 0.1,
            backend: str = "torch") -> dict[str, np.ndarray]:
    """Residues and estimates at every GPS sample.

    imu: (B, N, 6) specific force and body rate (FLU); gps: (B, K, 6) position and velocity
    (ENU); optional aiding streams, each with its timestamps: vio (B, M, 7) velocity and
    attitude quaternion (xyzw), mag (B, M, 3) body-frame magnetic field (gauss), baro (B, L, 1)
    height in the world frame (m; the caller removes the barometer's offset to the local
    origin). gps_std: (B, K, 6) the receiver's own std per fix (position m, velocity m/s) in
    place of the noise model's. Times in seconds, ``ekf0`` the filter state at ``t0``.

    Returns arrays (B, K, k): the residue groups of the streams given (dataset column groups)
    and ``est_pos``, ``est_vel``. ``backend``: ``torch`` (``OnlineFilter``, the closed loop's
    own arithmetic: its residues bit for bit) or ``numeric`` (``numeric.NumericFilter``, the
    compiled twin: the same to rounding).
    """
    B, K = gps.shape[0], gps.shape[1]
    aiding: dict[str, tuple[np.ndarray, torch.Tensor]] = {}
    for name, t, x in (("vio", vio_t, vio), ("mag", mag_t, mag), ("baro", baro_t, baro)):
        if (t is None) != (x is None):
            raise StreamError(f"{name}: timestamps and samples go together ({name}_t and {name}), got only one")
        if x is not None:
            aiding[name] = (t, x)
    for name, t, x in (("imu", imu_t, imu), ("gps", gps_t, gps), *((n, t, x) for n, (t, x) in aiding.items())):
        _check(name, t, x, B)
    if gps_std is not None:
        gps_std = torch.as_tensor(gps_std, dtype=torch.float64)
        _check_samples("gps_std", np.asarray(gps_t), gps_std, B)
        if gps_std.shape[1] != K:
            raise StreamError(f"gps_std: {gps_std.shape[1]} samples for {K} GPS samples")
        bad = ~(torch.isfinite(gps_std) & (gps_std > 0)).all(-1)
        if bad.any():
            b, i = (int(v) for v in torch.nonzero(bad)[0])
            raise StreamError(f"gps_std: non-positive or non-finite std at index {i} (flight {b})")
    imu_t, gps_t = (np.asarray(v, dtype=float) for v in (imu_t, gps_t))
    aiding = {n: (np.asarray(t, dtype=float), x) for n, (t, x) in aiding.items()}
    steps = np.diff(np.r_[t0, imu_t])
    if len(steps) and steps.max() > max_gap:
        i = int(np.argmax(steps))
        raise StreamError(f"imu: gap of {steps[i]:.3f} s before t = {imu_t[i]:.3f} s (more than {max_gap} s); "
                          f"split the log there")
    if backend == "torch":
        filt = OnlineFilter(ekf0, nm, dt, t0, gps_rate_hz, aiding=tuple(aiding), max_gap=max_gap)
    elif backend == "numeric":
        from quadformer.estimator.noise import Noise
        from quadformer.estimator.numeric.filter import NumericFilter

        e = {k: getattr(ekf0, k).numpy() for k in ("p", "v", "q", "P", "ba", "bg")}
        filt = NumericFilter(e["p"], e["v"], e["q"], e["P"], Noise.of(nm), dt, t0, gps_rate_hz, tuple(aiding),
                             max_gap, ba=e["ba"], bg=e["bg"])
    else:
        raise ValueError(f"backend: {backend!r} is not one of torch, numeric")
    out: dict[str, np.ndarray] = {}
    at = {name: 0 for name in aiding}
    ig = queued = 0
    eps = 1e-9
    for i, t in enumerate(imu_t):
        for name, (ts, xs) in aiding.items():          # queued, applied after this IMU step
            while at[name] < len(ts) and ts[at[name]] <= t + eps:
                filt.push(name, ts[at[name]], xs[:, at[name]])
                at[name] += 1
        while queued < K and gps_t[queued] <= t + eps:
            filt.push("gps", gps_t[queued], gps[:, queued], None if gps_std is None else gps_std[:, queued])
            queued += 1
        for _, row in filt.imu(t, imu[:, i]):
            for k, v in row.items():
                out.setdefault(k, np.zeros((B, K, v.shape[-1])))[:, ig] = np.asarray(v)
            ig += 1
    if ig < K:
        raise StreamError(f"gps: {K - ig} samples after the last IMU sample (t = {imu_t[-1] if len(imu_t) else t0})")
    return out
