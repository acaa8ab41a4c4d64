"""``NumericFilter``: ``online_filter.OnlineFilter`` for flights whose arithmetic runs compiled.

The same filter, reference and residues, sample for sample, as the torch ``OnlineFilter``
(``predict``, the VIO, magnetometer, barometer and GPS updates, ``ResidueTracker``,
``GpsFreeReference``), on numpy arrays with the per-sample work in ``kernels``: a log replayed
or a live vehicle costs microseconds per IMU sample instead of milliseconds. Its interface is
``OnlineFilter``'s with numpy samples in and numpy residue rows out; ``tests/test_numeric_filter.py``
holds the two to the same residues on a real log and on simulated flights.
"""

from __future__ import annotations

from collections import deque
from dataclasses import replace

import numpy as np

from quadformer.estimator.feed import AIDING, EPS, GapError, StreamError
from quadformer.estimator.noise import Noise
from quadformer.estimator.numeric import kernels
from quadformer.estimator.numeric.reference import Reference
from quadformer.estimator.schema import CORR_TAU, CORR_TAUS

__all__ = ["NumericFilter", "Tracker"]


def _selection(n: int, idx: range) -> np.ndarray:
    H = np.zeros((n, len(idx), 15))
    for j, k in enumerate(idx):
        H[:, j, k] = 1.0
    return H


class Tracker:
    """``residues.ResidueTracker`` on numpy arrays (its docstring states the residues)."""

    def __init__(self, n: int, gps_rate_hz: float, aiding: tuple[str, ...] = ("vio",), corr_tau: float = CORR_TAU):
        self.aiding = tuple(a for a in AIDING if a in aiding)
        self.corr = np.zeros((n, 3))
        self.decay = float(np.exp(-1.0 / (gps_rate_hz * corr_tau)))
        self.corrs = {name: np.zeros((n, 3)) for name in CORR_TAUS}
        self.decays = {name: float(np.exp(-1.0 / (gps_rate_hz * tau))) for name, tau in CORR_TAUS.items()}
        self.vio_r, self.vio_nis = np.zeros((n, 6)), np.zeros(n)
        self._sum, self._count = np.zeros(n), 0
        self.mag_r, self.mag_nis = np.zeros((n, 1)), np.zeros(n)
        self.baro_r, self.baro_nis = np.zeros((n, 1)), np.zeros(n)

    def on_vio(self, r: np.ndarray, nis: np.ndarray) -> None:
        self.vio_r, self.vio_nis = r, nis
        self._sum = self._sum + nis
        self._count += 1

    def on_gps(self, r, w, s_std, nis, dx) -> dict[str, np.ndarray]:
        self.corr = self.decay * self.corr + dx[:, 0:3]
        out = {"res_gps_r": r, "res_gps_w": w, "res_gps_s": s_std, "res_gps_nis": nis[:, None],
               "res_gps_corr": self.corr.copy()}
        for name, decay in self.decays.items():
            self.corrs[name] = decay * self.corrs[name] + dx[:, 0:3]
            out[name] = self.corrs[name].copy()
        if "vio" in self.aiding:
            out.update(res_vio_r=self.vio_r.copy(), res_vio_nis=self.vio_nis[:, None].copy(),
                       res_vio_nis_mean=(self._sum / max(self._count, 1))[:, None])
        if "mag" in self.aiding:
            out.update(res_mag_r=self.mag_r.copy(), res_mag_nis=self.mag_nis[:, None].copy())
        if "baro" in self.aiding:
            out.update(res_baro_r=self.baro_r.copy(), res_baro_nis=self.baro_nis[:, None].copy())
        self._sum = np.zeros_like(self._sum)
        self._count = 0
        return out


class NumericFilter:
    """The filter of ``n`` flights that share timestamps, started at t0 from position p, velocity
    v (n,3), attitude q (n,4) xyzw and covariance P (n,15,15) (biases zero), with noise ``noise``
    for IMU steps of dt seconds (other step lengths rescale it as ``OnlineFilter`` does not:
    both use ``noise`` as given, the step's length in the propagation)."""

    def __init__(self, p, v, q, P, noise: Noise, dt: float, t0: float = 0.0, gps_rate_hz: float = 10.0,
                 aiding: tuple[str, ...] = (), max_gap: float = 0.1, ba=None, bg=None):
        unknown = [a for a in aiding if a not in AIDING]
        if unknown:
            raise ValueError(f"aiding: unknown sensor {unknown[0]!r}; choose from {', '.join(AIDING)}")
        f64 = lambda a: np.array(a, dtype=np.float64, order="C")   # noqa: E731
        self.p, self.v, self.q, self.P = f64(p), f64(v), f64(q), f64(P)
        self.n = n = self.p.shape[0]
        self.ba = np.zeros((n, 3)) if ba is None else f64(ba)
        self.bg = np.zeros((n, 3)) if bg is None else f64(bg)
        self.noise, self.dt, self.t, self.max_gap = noise, float(dt), float(t0), float(max_gap)
        self.aiding = tuple(a for a in AIDING if a in aiding)
        self.tracker = Tracker(n, gps_rate_hz, aiding=self.aiding)
        self.reference = Reference(self.p, self.v, self.P, noise, gps_rate_hz, self.aiding)
        self.queues: dict[str, deque] = {name: deque() for name in (*self.aiding, "gps")}
        self._qdiag: dict[float, np.ndarray] = {}
        self._H = {"gps": _selection(n, range(0, 6)), "vio": _selection(n, range(3, 9)),
                   "baro": _selection(n, range(2, 3)), "mag": np.zeros((n, 1, 15))}
        self._out = {m: (np.empty((n, m)), np.empty(n), np.empty((n, m)), np.empty((n, 15))) for m in (1, 6)}

    # -- what the stream around it reads and sets ------------------------------------------------
    @property
    def position(self) -> np.ndarray:
        """The estimated position (n,3), ENU m."""
        return self.p.copy()

    @property
    def mag_field(self) -> np.ndarray | None:
        return self.noise.mag_field

    def set_mag_field(self, field: np.ndarray) -> None:
        """The Earth field (3,) (world, ENU) the magnetometer heading is measured against."""
        self.noise = replace(self.noise, mag_field=np.asarray(field, dtype=float))

    # -- samples ----------------------------------------------------------------------------------
    def push(self, stream: str, t: float, x, std=None) -> None:
        """Queue an aiding or GPS sample (n, k) stamped t, applied at the first IMU step at or
        after t. ``std``: GPS only, the receiver's own std per flight (n, 6)."""
        if stream not in self.queues:
            raise ValueError(f"{stream}: not a stream of this filter (it fuses {', '.join(self.queues)})")
        self.queues[stream].append((float(t), np.asarray(x, dtype=np.float64),
                                    None if std is None else np.asarray(std, dtype=np.float64)))

    def imu(self, t: float, x) -> list[tuple[float, dict[str, np.ndarray]]]:
        """Propagate to t with the IMU sample x (n, 6), then apply the queued samples stamped at
        or before t. Returns (stamp, residue row) per GPS fix applied, as ``OnlineFilter.imu``."""
        step = t - self.t
        if step > self.max_gap:
            raise GapError(f"imu: gap of {step:.3f} s before t = {t:.3f} s (more than {self.max_gap} s); "
                           f"split the log there")
        h = self.dt if abs(step - self.dt) < EPS else float(step)
        qd = self._qdiag.get(h)
        if qd is None:
            nm = self.noise
            qd = self._qdiag[h] = np.array([(nm.accel_std * h) ** 2] * 3 + [(nm.gyro_std * h) ** 2] * 3
                                           + [nm.accel_walk ** 2] * 3 + [nm.gyro_walk ** 2] * 3)
        ref = self.reference
        kernels.imu_step(self.p, self.v, self.q, self.ba, self.bg, self.P, ref.x, ref.C,
                         np.ascontiguousarray(x, dtype=np.float64).reshape(self.n, 6), h, qd,
                         self.noise.accel_std, ref.q_b)
        ref.elapse(h)
        self.t = t
        rows = []
        name, stamp = "imu", t
        try:
            for name in self.aiding:
                q = self.queues[name]
                while q and q[0][0] <= t + EPS:
                    stamp, sample, _ = q.popleft()
                    self._aid(name, sample)
            name, q = "gps", self.queues["gps"]
            while q and q[0][0] <= t + EPS:
                stamp, fix, std = q.popleft()
                rows.append((stamp, self._gps(fix, std)))
        except ValueError as e:         # a failed update, named by its stream and time
            raise StreamError(f"{name}: the filter's update failed at t = {stamp:.3f} s ({e}): a non-finite or "
                              "impossible sample, or a state the filter lost") from None
        return rows

    @property
    def pending(self) -> int:
        """Samples queued and not yet applied (they wait for an IMU sample at or after them)."""
        return sum(len(q) for q in self.queues.values())

    # -- the updates -----------------------------------------------------------------------------
    def _update(self, H, r, std):
        w, nis, s, dx = self._out[r.shape[1]]
        var = np.empty(r.shape)
        var[:] = std * std
        kernels.update(self.p, self.v, self.q, self.ba, self.bg, self.P, H, np.ascontiguousarray(r), var,
                       w, nis, s, dx)
        return r, w.copy(), nis.copy(), s.copy(), dx.copy()

    def _aid(self, name: str, x: np.ndarray) -> None:
        nm, tr = self.noise, self.tracker
        if name == "vio":
            r = np.empty((self.n, 6))
            kernels.vio_innovation(self.v, self.q, np.ascontiguousarray(x), r)
            r, _, nis, _, _ = self._update(self._H["vio"], r, nm.vio_std)
            tr.on_vio(r, nis)
            self.reference.vio(x[:, 0:3])
        elif name == "mag":
            r = np.empty((self.n, 1))
            H = self._H["mag"]
            kernels.mag_heading(self.q, np.ascontiguousarray(x), nm.mag_field, r, H)
            tr.mag_r, _, tr.mag_nis, _, _ = self._update(H, r, nm.mag_std)
        else:
            r = x - self.p[:, 2:3]
            tr.baro_r, _, tr.baro_nis, _, _ = self._update(self._H["baro"], r, nm.baro_std)
            self.reference.baro(x)

    def _gps(self, fix: np.ndarray, std: np.ndarray | None) -> dict[str, np.ndarray]:
        r = np.concatenate([fix[:, 0:3] - self.p, fix[:, 3:6] - self.v], axis=1)
        r, w, nis, s, dx = self._update(self._H["gps"], r, self.noise.gps_std if std is None else std)
        res = {**self.tracker.on_gps(r, w, s, nis, dx), **self.reference.on_gps(fix[:, 0:3], fix[:, 3:6], std)}
        self.reference.anchor(self.p, self.v, self.P)
        return {"est_pos": self.p.copy(), "est_vel": self.v.copy(), **res}
