"""The GPS-free reference (``estimator.reference``: its docstring states the design) on numpy
arrays: the same state, comparisons, anchor rule and resets, for ``n`` flights. Its
propagation runs in the compiled IMU step (``kernels.imu_step``); its VIO and barometer
updates in ``kernels.scalar_updates``."""

from __future__ import annotations

import math

import numpy as np

from quadformer.estimator.numeric import kernels
from quadformer.estimator.reference_config import ReferenceConfig

G = 9.81   # m/s^2


def axes_state(p: np.ndarray, v: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The reference state (n,3,3) and covariance (n,3,3,3) taken from the main filter's
    position p, velocity v (n,3) and covariance P (n,15,15) (``reference._axes_state``)."""
    n = p.shape[0]
    d = np.diagonal(P, axis1=1, axis2=2)
    ba = d[:, 9:12].max(-1)
    tilt = np.maximum(d[:, 6], d[:, 7])
    var_b = np.stack([ba + G * G * tilt, ba + G * G * tilt, ba], -1)
    x = np.stack([p, v, np.zeros_like(p)], -1)
    C = np.zeros((n, 3, 3, 3))
    for i in range(3):
        C[:, i, 0, 0] = P[:, i, i]
        C[:, i, 0, 1] = C[:, i, 1, 0] = P[:, i, 3 + i]
        C[:, i, 1, 1] = P[:, 3 + i, 3 + i]
    C[:, :, 2, 2] = var_b
    return x, C


def carry(e: np.ndarray, T: float) -> np.ndarray:
    """Offsets e (n,3,3) of the reference's state per axis (position, velocity, acceleration
    error) carried over T seconds of propagation without updates."""
    p = e[..., 0] + e[..., 1] * T - 0.5 * e[..., 2] * T * T
    return np.stack([p, e[..., 1] - e[..., 2] * T, e[..., 2]], -1)


class Reference:
    """The reference of ``n`` flights, started from the main filter's p, v, P; ``noise``: the
    filter's ``numeric.filter.Noise``."""

    def __init__(self, p: np.ndarray, v: np.ndarray, P: np.ndarray, noise, gps_rate_hz: float,
                 aiding: tuple[str, ...] = ("vio",), config: ReferenceConfig | None = None):
        if not (math.isfinite(gps_rate_hz) and gps_rate_hz > 0):
            raise ValueError(f"gps_rate_hz must be a positive number, got {gps_rate_hz!r}")
        self.cfg = c = ReferenceConfig() if config is None else config
        self.noise, self.rate, self.aiding = noise, float(gps_rate_hz), tuple(aiding)
        self.n = n = p.shape[0]
        self.x, self.C = axes_state(p, v, P)
        self.alpha = 1.0 - float(np.exp(-1.0 / (self.rate * c.smooth_tau)))
        self.alpha_v = 1.0 - float(np.exp(-1.0 / (self.rate * c.vel_tau)))
        self.lag = max(1, round(c.anchor_lag * self.rate))
        self.window = max(1, round(c.agree_window * self.rate))
        self.h_steps = tuple(max(1, round(h * self.rate)) for h in c.horizons)
        self.pv_steps = max(1, round(c.pv_horizon * self.rate))
        self.settle = round(2.0 * c.smooth_tau * self.rate)
        self.size = max(self.lag, *self.h_steps) + 1
        z = np.zeros
        self.a, self.vmean, self.vm_extra = z((n, 6)), z((n, 3)), z((n, 3))
        self.A, self.GA = z((n, 6)), z((n, 6))
        self.age = np.full(n, c.anchor_lag)
        self.count = np.zeros(n, dtype=np.int64)
        self.frozen = np.zeros(n, dtype=bool)
        self.drop = z((n, 6))
        self.hist = z((n, self.size, 12))
        self.gps_hist = z((n, self.pv_steps + 1, 6))
        self.steps = 0
        q_b = noise.accel_walk ** 2
        self.q_b = np.array([q_b + (G * noise.gyro_walk) ** 2] * 2 + [q_b])
        self._w = self._w_fresh = None
        # the reference less its continuation without resets, the shifts taken out of a, the
        # seconds propagated since e was carried (``reference.GpsFreeReference``)
        self.e, self.shifted, self.since = z((n, 3, 3)), z((n, 6)), 0.0

    def elapse(self, dt: float) -> None:
        """The reference was propagated over dt (in ``kernels.imu_step``): its offset from the
        continuation without resets follows, applied at the next update."""
        self.since += dt

    def _carry(self) -> None:
        if self.since:
            self.e = carry(self.e, self.since)
            self.since = 0.0

    def _aided(self, first: int, j: int, var: np.ndarray, r: np.ndarray) -> None:
        self._carry()
        ax = slice(first, first + r.shape[1])
        Cs = self.C[:, ax]
        K = Cs[..., :, j] / (Cs[..., j, j] + var)[..., None]
        kernels.scalar_updates(self.x, self.C, first, j, r, var)
        self.e[:, ax] = self.e[:, ax] - K * self.e[:, ax, j:j + 1]

    def vio(self, vel: np.ndarray) -> None:
        self._aided(0, 1, self.noise.vio_std[0:3] ** 2, vel - self.x[..., 1])

    def baro(self, height: np.ndarray) -> None:
        self._aided(2, 0, self.noise.baro_std ** 2, height - self.x[:, 2:3, 0])

    def _growth(self) -> np.ndarray:
        return np.concatenate([self.C[..., 0, 0], self.C[..., 1, 1]], -1) + self.drop

    def on_gps(self, pos: np.ndarray, vel: np.ndarray, std: np.ndarray | None = None) -> dict[str, np.ndarray]:
        c = self.cfg
        std = self.noise.gps_std if std is None else std
        if np.shape(std) != (self.n, 6):
            std = np.broadcast_to(std, (self.n, 6))
        d = np.concatenate([pos - self.x[..., 0], vel - self.x[..., 1]], -1)
        if self.steps == 0:
            self.a = d
            self.vmean = np.zeros_like(self.vmean)
            self.A = d.copy()
            self.hist[:] = np.concatenate([d, self._growth()], -1)[:, None]
            self.gps_hist[:] = np.concatenate([pos, vel], -1)[:, None]
            self.GA = self._growth()
        else:
            self.a = self.a + self.alpha * (d - self.a)
            self.vmean = self.vmean + self.alpha_v * (d[:, 3:] - self.vmean)
            self.vm_extra = self.vm_extra * (1.0 - self.alpha_v)
        Gt = self._growth()
        self.hist[:, self.steps % self.size] = np.concatenate([self.a, Gt], -1)
        self.gps_hist[:, self.steps % (self.pv_steps + 1)] = np.concatenate([pos, vel], -1)
        self.steps += 1

        white = std * std
        white = np.concatenate([np.maximum(white[:, :3] - c.gps_slow_std ** 2, 0.25 * white[:, :3]), white[:, 3:]],
                               -1)
        gps_var = white * (self.alpha / (2.0 - self.alpha))
        Pvv = self.C[..., 1, 1]

        self.age = self.age + 1.0 / self.rate
        # the four comparisons whitened together (element by element the same arithmetic as one by
        # one): against the anchor, the two horizons back, and the anchor as it would be refreshed
        d = self.a - self.A
        diffs, then_g, seconds = [d], [self.GA], [self.age]
        names = ("res_ref_h5", "res_ref_h30")[:len(self.h_steps)]
        for h in self.h_steps[:len(names)]:
            k = max(0, min(h, self.steps - 1 - self.settle))
            then = self.hist[:, (self.steps - 1 - k) % self.size]
            diffs.append(self.a - then[:, :6])
            then_g.append(then[:, 6:])
            seconds.append(np.full(self.n, k / self.rate))
        diffs.append(d)
        then_g.append(self.GA)
        seconds.append(np.full(self.n, self.lag / self.rate))
        grow = np.maximum(Gt - np.array(then_g), 0.0)
        slow = 2.0 * c.gps_slow_std ** 2 * (1.0 - np.exp(-np.array(seconds) / c.gps_slow_tau))
        var_p = grow[..., :3] + 2.0 * gps_var[:, :3] + slow[..., None]
        var_v = grow[..., 3:] + 2.0 * Pvv + 2.0 * gps_var[:, 3:]
        w, *back, fresh = np.array(diffs) / np.sqrt(np.concatenate([var_p, var_v], -1))
        out = {"res_ref_d": d, "res_ref_w": w, **dict(zip(names, back))}
        e = self.vm_extra
        var_m = std[:, 3:] ** 2 * (self.alpha_v / (2.0 - self.alpha_v)) + Pvv + e * (2.0 * np.sqrt(Pvv) + e)
        out["res_ref_vmean"] = self.vmean / np.sqrt(var_m)
        out["res_ref_age"] = self.age[:, None].copy()
        self._carry()
        out["res_ref_reset"] = np.concatenate([self.e[..., 0], self.e[..., 1]], -1) - self.shifted
        k = min(self.pv_steps, self.steps - 1)
        if k == 0:
            out["res_gps_pv"] = np.zeros((self.n, 3))
        else:
            ring = self.pv_steps + 1
            idx = [(self.steps - 1 - i) % ring for i in range(k + 1)]
            fixes = self.gps_hist[:, idx]
            vbar = (fixes[:, 1:-1, 3:].sum(1) + 0.5 * (fixes[:, 0, 3:] + fixes[:, -1, 3:])) / k
            span = k / self.rate
            dv = vbar - (fixes[:, 0, :3] - fixes[:, -1, :3]) / span
            var = 2.0 * std[:, :3] ** 2 / span ** 2 + std[:, 3:] ** 2 / k
            out["res_gps_pv"] = dv / np.sqrt(var)
        self._w, self._w_fresh = w, fresh
        return out

    def anchor(self, p: np.ndarray, v: np.ndarray, P: np.ndarray) -> None:
        """After this step's residues and the main filter's update (its p, v, P)."""
        c = self.cfg
        big = np.where(self.frozen, np.abs(self._w_fresh[:, :2]).max(-1) / c.release_k,
                       np.abs(self._w[:, :2]).max(-1) / c.agree_k)
        agree = big < 1.0
        self.frozen = self.frozen | ~agree
        self.count = np.where(agree, self.count + 1, 0)
        follow = (self.count >= self.window) | (self.steps <= self.window + self.lag)
        self.frozen = self.frozen & ~follow
        if follow.any():
            k = min(self.lag, self.steps - 1)
            then = self.hist[:, (self.steps - 1 - k) % self.size]
            f = follow[:, None]
            self.A = np.where(f, then[:, :6], self.A)
            self.GA = np.where(f, then[:, 6:], self.GA)
            self.age = np.where(follow, k / self.rate, self.age)
            std_h = np.sqrt(np.maximum(self.C[:, 0, 0, 0], self.C[:, 1, 0, 0]))
            reset = follow & (std_h > c.reset_std)
            if reset.any():
                self._reset(p, v, P, reset)

    def _reset(self, p, v, P, mask: np.ndarray) -> None:
        x, C = axes_state(p, v, P)
        m = mask[:, None]
        jump = np.concatenate([x[..., 0] - self.x[..., 0], x[..., 1] - self.x[..., 1]], -1)
        jump = np.where(m, jump, 0.0)
        self.e = self.e + np.where(mask[:, None, None], x - self.x, 0.0)
        self.shifted = self.shifted + jump
        before = self._growth()
        self.vm_extra = np.where(m, self.vm_extra + np.sqrt(self.C[..., 1, 1]), self.vm_extra)
        self.x = np.where(mask[:, None, None], x, self.x)
        self.C = np.where(mask[:, None, None, None], C, self.C)
        self.drop = self.drop + np.where(m, before - self._growth(), 0.0)
        self.a = self.a - jump
        self.A = self.A - jump
        self.vmean = self.vmean - jump[:, 3:]
        self.hist[..., :6] = self.hist[..., :6] - jump[:, None]
