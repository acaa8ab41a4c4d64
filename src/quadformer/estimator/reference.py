"""A GPS-free reference carried beside the main filter, and residues that last as long as a spoof.

The main filter absorbs a GPS bias within seconds: its innovation fades while the spoof goes
on. The reference never fuses GPS, so the difference d = GPS - reference keeps the spoof for
as long as the reference stays accurate. The reference is a Kalman filter per world axis on
(position, velocity, acceleration error), propagated with the main filter's world-frame
acceleration R(q) (f - b_a) + g (the IMU sample through the main filter's attitude and
accelerometer bias, which a position or velocity spoof barely moves) and corrected by the
VIO velocity and the barometric height, never by GPS. With VIO its velocity is absolute and
its position drifts slowly; without VIO (IMU, magnetometer, barometer) only its height is
held and its horizontal state drifts within seconds, which its covariance says.

At each GPS step the difference d (position, velocity) is smoothed (``smooth_tau``) into a,
and compared

- with an anchor A, a value of a from a time when GPS agreed with the reference
  (``res_ref_d`` in metres, ``res_ref_w`` whitened; ``res_ref_age`` the anchor's age): the
  anchor follows ``anchor_lag`` seconds behind while both whitened horizontal position
  components of a - A have stayed below ``agree_k`` for ``agree_window`` seconds (and, while
  the smoothing settles during the first ``agree_window`` + ``anchor_lag`` seconds,
  regardless); a disagreement freezes it, and it follows again only after both, whitened as
  if the anchor were fresh (``anchor_lag`` old: GPS has come back to where the anchor is),
  have stayed below ``release_k`` for ``agree_window`` seconds. The vertical is left out of
  the rule (GPS height is the noisiest component). A spoof's offset therefore never enters
  the anchor and stays in a - A while the spoof lasts; its whitened size falls as the
  anchor ages, because the GPS's own slow error may wander as far (which the whitening
  states), while the anchor's age keeps growing;
- with itself ``horizons`` seconds earlier (``res_ref_h5``, ``res_ref_h30``; never earlier
  than two smoothing time constants after the start, 0 until then);
- the velocity difference is also averaged over ``vel_tau`` seconds (``res_ref_vmean``): with
  VIO the reference's velocity is absolute, so a drift spoofed with a matching velocity
  stays in it for the whole attack.

Every comparison is whitened by what a clean flight explains: the reference's covariance
growth over the interval (velocity: plus twice its current variance, the
errors at both ends), the white GPS noise left after smoothing at both ends and, for
position, the change of the GPS's slowly varying error (``gps_slow_std``, ``gps_slow_tau``;
the fix's position variance minus the slow part is taken as white) over the interval.

Also GPS-only: the GPS velocity averaged over ``pv_horizon`` against the change of GPS
position over it (``res_gps_pv``): a spoofer who moves the position without matching the
velocity (or the reverse) shows there for as long as he does.

When the reference's horizontal position std exceeds ``reset_std`` (without VIO, every few
seconds) and GPS agrees, its position and velocity are reset to the main filter's; a and the
anchor are shifted by the same amount, so the comparisons stay continuous. The shift is a
constant, while the velocity a reset gives the reference goes on moving its position (and its
acceleration error, set to zero, its velocity): a reset while a drift GPS agrees with is on
takes in the spoofed velocity the main filter has followed, and from then on the reference runs
with the drift. For the shape typer, ``res_ref_reset`` is the reference less its continuation
without resets (the same propagation and the same updates, at the reset reference's gains,
from its state before them), less the shifts taken out of a: added to a's raw rows it gives
GPS minus that continuation, whose position is the sum of its velocity (exactly so on an axis
without updates: the horizontal without VIO). It is no detector input; the other residues do
not depend on it.
"""

from __future__ import annotations

import math

import numpy as np
import roma
import torch

from quadformer.estimator.eskf import GRAVITY, EKFState, NoiseModel
from quadformer.estimator.reference_config import ReferenceConfig
from quadformer.geometry import bmm, matvec

G = 9.81   # m/s^2


def _axes_state(ekf: EKFState) -> tuple[torch.Tensor, torch.Tensor]:
    """The reference state (B,3,3) per axis (position, velocity, acceleration error) and its
    covariance (B,3,3,3) taken from the main filter: its position and velocity blocks per axis,
    and the acceleration error its attitude and accelerometer bias uncertainty allow."""
    B = ekf.p.shape[0]
    P = ekf.P
    d = torch.diagonal(P, dim1=1, dim2=2)                        # (B,15)
    ba = d[:, 9:12].max(-1).values
    tilt = torch.maximum(d[:, 6], d[:, 7])
    var_b = torch.stack([ba + G * G * tilt, ba + G * G * tilt, ba], -1)   # (B,3)
    x = torch.stack([ekf.p, ekf.v, torch.zeros_like(ekf.p)], -1)
    C = torch.zeros(B, 3, 3, 3, dtype=torch.float64)
    for i in range(3):
        C[:, i, 0, 0] = P[:, i, i]
        C[:, i, 0, 1] = C[:, i, 1, 0] = P[:, i, 3 + i]
        C[:, i, 1, 1] = P[:, 3 + i, 3 + i]
    C[:, :, 2, 2] = var_b
    return x, C


def _scalar_update(x, C, axes, j, r, var, e=None):
    """Kalman update of the state component j on the axes ``axes`` with innovation r (B,k) and
    noise variance var (k,); ``e`` (B,3,3): offsets of the state the same update moves by its
    gain (returned third where given)."""
    xs, Cs = x[:, axes], C[:, axes]                  # (B,k,3), (B,k,3,3)
    col = Cs[..., :, j]                              # (B,k,3)
    s = Cs[..., j, j] + var                          # (B,k)
    K = col / s.unsqueeze(-1)
    xs = xs + K * r.unsqueeze(-1)
    Cs = Cs - K.unsqueeze(-1) * col.unsqueeze(-2)
    Cs = 0.5 * (Cs + Cs.transpose(-1, -2))
    x, C = x.clone(), C.clone()
    x[:, axes], C[:, axes] = xs, Cs
    if e is None:
        return x, C
    e = e.clone()
    e[:, axes] = e[:, axes] - K * e[:, axes, j:j + 1]
    return x, C, e


def carry(e: torch.Tensor, T: float) -> torch.Tensor:
    """Offsets e (B,3,3) of the reference's state per axis (position, velocity, acceleration
    error) carried over T seconds of propagation without updates."""
    p = e[..., 0] + e[..., 1] * T - 0.5 * e[..., 2] * T * T
    return torch.stack([p, e[..., 1] - e[..., 2] * T, e[..., 2]], -1)


class GpsFreeReference:
    """The reference for a batch of ``n`` flights, started from the main filter's state."""

    def __init__(self, ekf0: EKFState, nm: NoiseModel, gps_rate_hz: float, aiding: tuple[str, ...] = ("vio",),
                 config: ReferenceConfig | None = None):
        if not (math.isfinite(gps_rate_hz) and gps_rate_hz > 0):
            raise ValueError(f"gps_rate_hz must be a positive number, got {gps_rate_hz!r}")
        self.cfg = c = ReferenceConfig() if config is None else config
        self.nm, self.rate, self.aiding = nm, float(gps_rate_hz), tuple(aiding)
        self.n = n = ekf0.p.shape[0]
        self.x, self.C = _axes_state(ekf0)
        self.alpha = 1.0 - float(np.exp(-1.0 / (self.rate * c.smooth_tau)))
        self.alpha_v = 1.0 - float(np.exp(-1.0 / (self.rate * c.vel_tau)))
        self.lag = max(1, round(c.anchor_lag * self.rate))
        self.window = max(1, round(c.agree_window * self.rate))
        self.h_steps = tuple(max(1, round(h * self.rate)) for h in c.horizons)
        self.pv_steps = max(1, round(c.pv_horizon * self.rate))
        self.settle = round(2.0 * c.smooth_tau * self.rate)     # steps the smoothing needs to settle
        self.size = max(self.lag, *self.h_steps) + 1
        z = lambda *s: torch.zeros(*s, dtype=torch.float64)  # noqa: E731
        self.a, self.vmean = z(n, 6), z(n, 3)
        self.vm_extra = z(n, 3)                 # std of the reference errors resets shifted into vmean
        self.A, self.GA = z(n, 6), z(n, 6)      # anchor: smoothed difference, covariance growth
        self.age = torch.full((n,), c.anchor_lag, dtype=torch.float64)
        self.count = torch.zeros(n, dtype=torch.long)        # consecutive agreeing steps
        self.frozen = torch.zeros(n, dtype=torch.bool)       # a disagreement since the last release
        self.drop = z(n, 6)                     # covariance removed by resets (keeps growth continuous)
        self.hist = z(n, self.size, 12)         # ring: a (6), growth G (6)
        self.gps_hist = z(n, self.pv_steps + 1, 6)
        self.steps = 0
        q_b = nm.accel_walk ** 2
        self.q_b = torch.tensor([q_b + (G * nm.gyro_walk) ** 2] * 2 + [q_b], dtype=torch.float64)
        self._F: dict[float, torch.Tensor] = {}
        # the reference less its continuation without resets (the same propagation and updates
        # from its state before them), per axis; the offsets the resets shifted out of a; the
        # seconds propagated since e was last carried
        self.e, self.shifted, self.since = z(n, 3, 3), z(n, 6), 0.0

    # -- the filter --------------------------------------------------------------------
    def predict(self, ekf: EKFState, accel: torch.Tensor, dt: float) -> None:
        """Propagate over dt with the IMU specific force ``accel`` (B,3) seen through the main
        filter's state ``ekf`` before its own propagation with the same sample."""
        R = roma.unitquat_to_rotmat(ekf.q)
        a = matvec(R, accel - ekf.ba) + GRAVITY - self.x[..., 2]
        p = self.x[..., 0] + self.x[..., 1] * dt + 0.5 * a * dt * dt
        v = self.x[..., 1] + a * dt
        self.x = torch.stack([p, v, self.x[..., 2]], -1)
        F = self._F.get(dt)
        if F is None:
            F = self._F[dt] = torch.tensor([[1.0, dt, -0.5 * dt * dt], [0.0, 1.0, -dt], [0.0, 0.0, 1.0]],
                                           dtype=torch.float64)
        C = bmm(bmm(F.expand_as(self.C), self.C), F.T.expand_as(self.C))
        C[..., 1, 1] += (self.nm.accel_std * dt) ** 2
        C[..., 2, 2] += self.q_b
        self.C = C
        self.since += dt

    def _carry(self) -> None:
        if self.since:
            self.e = carry(self.e, self.since)
            self.since = 0.0

    def vio(self, vel: torch.Tensor) -> None:
        """VIO velocity (B,3), world frame."""
        var = self.nm.vio_std[0:3].to(torch.float64) ** 2
        self._carry()
        self.x, self.C, self.e = _scalar_update(self.x, self.C, [0, 1, 2], 1, vel - self.x[..., 1], var, self.e)

    def baro(self, height: torch.Tensor) -> None:
        """Barometric height (B,1), world frame."""
        var = self.nm.baro_std.to(torch.float64) ** 2
        self._carry()
        self.x, self.C, self.e = _scalar_update(self.x, self.C, [2], 0, height - self.x[:, 2:3, 0], var, self.e)

    # -- the residues ------------------------------------------------------------------
    def _growth(self) -> torch.Tensor:
        """(B,6): position and velocity variance per axis plus what resets removed."""
        return torch.cat([self.C[..., 0, 0], self.C[..., 1, 1]], -1) + self.drop

    def on_gps(self, pos: torch.Tensor, vel: torch.Tensor, std: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """The residues of this GPS fix (each (B,k)); ``std`` (6,) or (B,6): the fix's position and
        velocity std (default the noise model's). Call ``anchor`` after the main filter's update."""
        c = self.cfg
        std = (self.nm.gps_std if std is None else std).to(torch.float64).expand(self.n, 6)
        d = torch.cat([pos - self.x[..., 0], vel - self.x[..., 1]], -1)
        if self.steps == 0:
            self.a = d
            self.vmean = torch.zeros_like(self.vmean)
            self.A = d.clone()
            self.hist[:] = torch.cat([d, self._growth()], -1).unsqueeze(1)
            self.gps_hist[:] = torch.cat([pos, vel], -1).unsqueeze(1)
            self.GA = self._growth()
        else:
            self.a = self.a + self.alpha * (d - self.a)
            self.vmean = self.vmean + self.alpha_v * (d[:, 3:] - self.vmean)
            self.vm_extra = self.vm_extra * (1.0 - self.alpha_v)
        Gt = self._growth()
        slot = self.steps % self.size
        self.hist[:, slot] = torch.cat([self.a, Gt], -1)
        self.gps_hist[:, self.steps % (self.pv_steps + 1)] = torch.cat([pos, vel], -1)
        self.steps += 1

        # the GPS noise left after smoothing, at one end: its white part (the slow part apart)
        white = std * std
        white = torch.cat([torch.maximum(white[:, :3] - c.gps_slow_std ** 2, 0.25 * white[:, :3]), white[:, 3:]], -1)
        gps_var = white * (self.alpha / (2.0 - self.alpha))
        Pvv = self.C[..., 1, 1]

        def whiten(diff, G_then, seconds):
            grow = torch.clamp(Gt - G_then, min=0.0)
            slow = 2.0 * c.gps_slow_std ** 2 * (1.0 - torch.exp(-torch.as_tensor(seconds) / c.gps_slow_tau))
            var_p = grow[:, :3] + 2.0 * gps_var[:, :3] + slow.reshape(-1, 1)
            var_v = grow[:, 3:] + 2.0 * Pvv + 2.0 * gps_var[:, 3:]
            return diff / torch.sqrt(torch.cat([var_p, var_v], -1))

        self.age = self.age + 1.0 / self.rate
        w = whiten(self.a - self.A, self.GA, self.age)
        out = {"res_ref_d": self.a - self.A, "res_ref_w": w}
        for name, h in zip(("res_ref_h5", "res_ref_h30"), self.h_steps):
            k = max(0, min(h, self.steps - 1 - self.settle))      # never back into the smoothing's start
            then = self.hist[:, (self.steps - 1 - k) % self.size]
            out[name] = whiten(self.a - then[:, :6], then[:, 6:], torch.full((self.n,), k / self.rate))
        # the reference's error in the average: its current velocity variance, plus what a reset
        # shifted in (the errors averaged before it, up to the std the reference had then), fading
        # as the average renews
        e = self.vm_extra
        var_m = std[:, 3:] ** 2 * (self.alpha_v / (2.0 - self.alpha_v)) + Pvv + e * (2.0 * torch.sqrt(Pvv) + e)
        out["res_ref_vmean"] = self.vmean / torch.sqrt(var_m)
        out["res_ref_age"] = self.age.unsqueeze(-1)
        self._carry()
        out["res_ref_reset"] = torch.cat([self.e[..., 0], self.e[..., 1]], -1) - self.shifted
        k = min(self.pv_steps, self.steps - 1)
        if k == 0:
            out["res_gps_pv"] = torch.zeros(self.n, 3, dtype=torch.float64)
        else:
            ring = self.pv_steps + 1
            idx = [(self.steps - 1 - i) % ring for i in range(k + 1)]
            fixes = self.gps_hist[:, idx]                               # newest first
            vbar = (fixes[:, 1:-1, 3:].sum(1) + 0.5 * (fixes[:, 0, 3:] + fixes[:, -1, 3:])) / k
            span = k / self.rate
            dv = vbar - (fixes[:, 0, :3] - fixes[:, -1, :3]) / span
            var = 2.0 * std[:, :3] ** 2 / span ** 2 + std[:, 3:] ** 2 / k
            out["res_gps_pv"] = dv / torch.sqrt(var)
        # the same difference against the noise of a fresh anchor (anchor_lag old): whether GPS
        # has come back to where the anchor is, for the release of a frozen anchor
        self._w, self._w_fresh = w, whiten(self.a - self.A, self.GA, torch.full((self.n,), self.lag / self.rate))
        return out

    def anchor(self, ekf: EKFState) -> None:
        """After this step's residues and the main filter's update (``ekf``): the anchor follows,
        freezes or stays frozen, and a reference too uncertain is reset to the main filter."""
        c = self.cfg
        big = torch.where(self.frozen, self._w_fresh[:, :2].abs().max(-1).values / c.release_k,
                          self._w[:, :2].abs().max(-1).values / c.agree_k)
        agree = big < 1.0
        self.frozen = self.frozen | ~agree
        self.count = torch.where(agree, self.count + 1, torch.zeros_like(self.count))
        # until the smoothing has settled (the first window and lag) the anchor follows regardless
        follow = (self.count >= self.window) | (self.steps <= self.window + self.lag)
        self.frozen = self.frozen & ~follow
        if bool(follow.any()):
            k = min(self.lag, self.steps - 1)
            then = self.hist[:, (self.steps - 1 - k) % self.size]
            f = follow.unsqueeze(-1)
            self.A = torch.where(f, then[:, :6], self.A)
            self.GA = torch.where(f, then[:, 6:], self.GA)
            self.age = torch.where(follow, torch.full_like(self.age, k / self.rate), self.age)
            std_h = torch.sqrt(torch.maximum(self.C[:, 0, 0, 0], self.C[:, 1, 0, 0]))
            reset = follow & (std_h > c.reset_std)
            if bool(reset.any()):
                self._reset(ekf, reset)

    def _reset(self, ekf: EKFState, mask: torch.Tensor) -> None:
        x, C = _axes_state(ekf)
        m = mask.view(-1, 1)
        jump = torch.cat([x[..., 0] - self.x[..., 0], x[..., 1] - self.x[..., 1]], -1)
        jump = torch.where(m, jump, torch.zeros_like(jump))
        self.e = self.e + torch.where(mask.view(-1, 1, 1), x - self.x, torch.zeros_like(x))
        self.shifted = self.shifted + jump
        before = self._growth()
        self.vm_extra = torch.where(m, self.vm_extra + torch.sqrt(self.C[..., 1, 1]), self.vm_extra)
        self.x = torch.where(mask.view(-1, 1, 1), x, self.x)
        self.C = torch.where(mask.view(-1, 1, 1, 1), C, self.C)
        self.drop = self.drop + torch.where(m, before - self._growth(), torch.zeros_like(before))
        # GPS minus reference drops by the jump: shift the smoothed difference, its history and the
        # anchor by the same amount, so every comparison stays continuous
        self.a = self.a - jump
        self.A = self.A - jump
        self.vmean = self.vmean - jump[:, 3:]
        self.hist[..., :6] = self.hist[..., :6] - jump.unsqueeze(1)
