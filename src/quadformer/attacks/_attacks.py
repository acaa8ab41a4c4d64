"""Attack sampling and application on the GPS fix.

Each attacked flight has one attack window [onset, onset + duration) clipped to the
flight. ``d`` acts on a random non-empty subset of axes that holds at least one
horizontal axis (or the axes fixed by the config):

- ``bias`` (Attack I): constant offset of norm ``magnitude`` from the onset.
- ``ramp`` (Attack II): offset growing at ``rate`` m/s along a horizontal direction, and
  the GPS velocity shifted by the same drift velocity (a coordinated, consistent drift).
- ``sinusoid``: offset ``magnitude * sin(2 pi f tau)``, velocity shifted consistently.
- ``intermittent``: the bias switched on for the first half of each ``period``.
- ``replay``: the whole fix replaced by the honest fix recorded ``delay`` seconds earlier.
- ``freeze``: the whole fix held at its value at the onset.
- ``drift``: a consistent drift along a horizontal direction u, d(tau) = u s(tau) with the GPS
  velocity shifted by u s'(tau): switched on at once (``onset_step``: s = rate tau, the
  velocity steps to ``rate``; the same offsets as ``ramp``), or accelerating in at ``accel``
  without a velocity step (s = accel tau^2 / 2 until tau = rate / accel, then growing at
  ``rate``).
- ``capture``: an SDR capture: the fix pulled off by ``magnitude`` along a horizontal direction
  over ``capture_s`` on an s-curve (h(x) = 3x^2 - 2x^3, x = tau / capture_s) while a drift at
  ``rate`` ramps in with it (its velocity ``rate`` h(x)), then drifting on at ``rate``; the GPS
  velocity is the offset's derivative throughout. Beside the fix, the receiver's own reports
  (``receiver_effects``): satellites, accuracies, noise and a brief loss of lock.

The label of a GPS sample is 1 when it is falsified: inside the window, and for
``intermittent`` only while the injection is on.

Mixed attacks (``AttackConfig(kind="mix")``): each flight first draws its kind uniformly
from ``mix`` (one extra draw from its scenario generator, made only for mixed attacks, so a
single-kind configuration draws exactly what it drew before mixed attacks existed), then
its parameters from that kind's ranges. A batch holds one kind per flight.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

from quadformer.config import HORIZONTAL_KINDS, MIX, STEALTH, AttackConfig

_SUBSETS = ("x", "y", "xy", "xz", "yz", "xyz")
_HORIZONTAL = ("x", "y", "xy")

#: a capture's receiver signature, each drawn per flight from its range (low, high): the share of
#: satellites left at the capture's deepest, the multipliers of eph (and epv) and of the speed
#: accuracy at their peak, the rise of the noise indicator while the spoofer transmits (a share), and
#: the time (s) the receiver takes after the pull-off to recover its satellites and accuracies
CAPTURE_RECEIVER = {"sat_share": (0.4, 0.5), "eph_gain": (3.0, 4.5), "speed_acc_gain": (8.0, 14.0),
                    "noise_rise": (0.3, 0.4), "recover_s": (4.0, 6.0)}


def smoothstep(x: np.ndarray) -> np.ndarray:
    """3x^2 - 2x^3 of x clipped to [0, 1]: 0 to 1 with zero slope at both ends."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


@dataclass(frozen=True)
class AttackBatch:
    kind: np.ndarray         # (B,) each flight's attack kind ("none" when not attacked)
    attacked: np.ndarray     # (B,) bool
    onset: np.ndarray        # (B,) s (nan when not attacked)
    end: np.ndarray          # (B,) s, exclusive, clipped to the flight
    axes: np.ndarray         # (B,) attacked axes, e.g. "xy" ("" when not attacked)
    direction: np.ndarray    # (B,3) unit vector on the attacked axes
    magnitude: np.ndarray    # (B,) m
    rate: np.ndarray         # (B,) m/s
    frequency: np.ndarray    # (B,) Hz
    period: np.ndarray       # (B,) s
    delay: np.ndarray        # (B,) s
    accel: np.ndarray        # (B,) m/s^2, a drift's acceleration while it ramps in (nan: not a drift)
    onset_step: np.ndarray   # (B,) bool, a drift switched on at once (its velocity steps to the rate)
    capture_s: np.ndarray    # (B,) s, a capture's pull-off time (nan: not a capture)
    lock_loss_s: np.ndarray  # (B,) s, the fix lost from a capture's onset
    sat_share: np.ndarray    # (B,) 1, satellites left at a capture's deepest, as a share
    eph_gain: np.ndarray     # (B,) 1, eph and epv multiplier at a capture's peak
    speed_acc_gain: np.ndarray  # (B,) 1, speed accuracy multiplier at a capture's peak
    noise_rise: np.ndarray   # (B,) 1, rise of the noise indicator while a capture lasts (a share)
    recover_s: np.ndarray    # (B,) s, the receiver's recovery after a capture's pull-off

    def window(self, t: float) -> np.ndarray:
        """Flights whose attack window contains time t."""
        with np.errstate(invalid="ignore"):
            return self.attacked & (t >= self.onset) & (t < self.end)

    def apply(self, t: float, j: int, pos: torch.Tensor, vel: torch.Tensor,
              history: torch.Tensor, rate_hz: float):
        """Attacked GPS fix at GPS step j (time t), each flight under its own kind.

        pos, vel: (B,3) honest fix; history: (B, n_gps, 6) honest fixes so far (replay and
        freeze read it). Returns (pos, vel, label (B,) bool, d_pos (B,3), d_vel (B,3)).
        """
        B = pos.shape[0]
        zero = np.zeros((B, 3))
        active = self.window(t)
        if not active.any():
            return pos, vel, active, zero, zero
        tau = np.where(active, t - self.onset, 0.0)
        d_pos, d_vel = zero.copy(), zero.copy()
        for kind in np.unique(self.kind[active]):
            m = active & (self.kind == kind)
            dp, dv, on = self._offset(str(kind), m, tau, j, pos, vel, history, rate_hz)
            d_pos[m], d_vel[m] = dp[m], dv[m]
            if on is not None:
                active = active & (on | ~m)
        m = active[:, None]
        d_pos = np.where(m, d_pos, 0.0)
        d_vel = np.where(m, d_vel, 0.0)
        return (pos + torch.from_numpy(d_pos), vel + torch.from_numpy(d_vel), active, d_pos, d_vel)

    def _offset(self, kind: str, m: np.ndarray, tau: np.ndarray, j: int, pos: torch.Tensor, vel: torch.Tensor,
                history: torch.Tensor, rate_hz: float):
        """Position and velocity offsets (B,3) of attack ``kind``, valid on the flights ``m``
        (computed for every flight, so a flight's arithmetic does not depend on the others),
        and for ``intermittent`` whether the injection is on (else None)."""
        B = pos.shape[0]
        u = self.direction
        zero = np.zeros((B, 3))
        if kind == "bias":
            return self.magnitude[:, None] * u, zero, None
        if kind == "ramp":
            return (self.rate * tau)[:, None] * u, self.rate[:, None] * u, None
        if kind == "sinusoid":
            w = 2 * np.pi * self.frequency
            return (self.magnitude * np.sin(w * tau))[:, None] * u, (self.magnitude * w * np.cos(w * tau))[:, None] * u, None
        if kind == "intermittent":
            period = np.where(m, self.period, 1.0)
            return self.magnitude[:, None] * u, zero, np.mod(tau, period) < 0.5 * period
        if kind == "drift":
            r = self.rate
            a = np.where(m, self.accel, 1.0)
            top = r / a                                       # s, when the accelerating drift reaches its rate
            s_acc = np.where(tau < top, 0.5 * a * tau * tau, 0.5 * a * top * top + r * (tau - top))
            v_acc = np.where(tau < top, a * tau, r)
            step = self.onset_step.astype(bool)
            s, v = np.where(step, r * tau, s_acc), np.where(step, r, v_acc)
            return s[:, None] * u, v[:, None] * u, None
        if kind == "capture":
            s, v = self._capture(m, tau)
            return s[:, None] * u, v[:, None] * u, None
        if kind in ("replay", "freeze"):
            if kind == "replay":
                src = j - np.round(np.where(m, self.delay, 0.0) * rate_hz).astype(int)
            else:
                src = np.round(np.where(m, self.onset, 0.0) * rate_hz).astype(int) - 1   # the last honest fix
            src = np.clip(np.where(m, src, j), 0, j)
            fake = history[torch.arange(B), torch.as_tensor(src)].numpy()
            honest = torch.cat([pos, vel], -1).numpy()
            diff = fake - honest
            return diff[:, :3], diff[:, 3:], None
        if kind == STEALTH:
            raise ValueError("a stealthy attack has no fixed shape: its attacker chooses each fix as the flight "
                             "goes (attacks.StealthyAttacker, in the closed loop)")
        raise ValueError(f"unknown attack kind {kind!r}")   # pragma: no cover - the config validates kinds

    def _capture(self, m: np.ndarray, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A capture's offset along its direction (m) and its derivative (m/s) at tau (s since
        the onset): magnitude h(x) plus a drift whose speed ramps in as rate h(x), x = tau / capture_s,
        then rate."""
        c = np.where(m, self.capture_s, 1.0)
        x = np.clip(tau / c, 0.0, 1.0)
        h = smoothstep(x)
        drift = self.rate * (c * (x ** 3 - 0.5 * x ** 4) + np.maximum(tau - c, 0.0))   # the integral of rate h
        s = self.magnitude * h + drift
        v = self.magnitude * 6.0 * x * (1.0 - x) / c + self.rate * h
        return s, v

    def receiver_effects(self, t) -> dict[str, np.ndarray]:
        """The receiver's reports under each flight's attack at time(s) ``t`` (s, the attack's clock):
        per flight (B,) for a scalar t, (T, B) for t of shape (T,). Factors on what a clean
        receiver reports (1 where unchanged): ``satellites``, ``eph``, ``epv``, ``speed_acc``,
        ``noise``; and ``fix_lost`` (bool): no fix (fix type 1). Only a capture changes them, inside
        its window: an envelope e rising 0 -> 1 over the pull-off (smoothstep) and falling back over
        ``recover_s`` after it scales the satellites (1 - (1 - sat_share) e), eph and epv
        (1 + (eph_gain - 1) e) and the speed accuracy (1 + (speed_acc_gain - 1) e); the noise
        indicator rises by noise_rise over the pull-off and stays up while the spoof lasts; the fix is
        lost for ``lock_loss_s`` from the onset."""
        t = np.asarray(t, dtype=float)[..., None]
        cap = self.attacked & (self.kind == "capture")
        with np.errstate(invalid="ignore"):
            on = cap & (t >= self.onset) & (t < self.end)
        tau = np.where(on, t - np.where(cap, self.onset, 0.0), 0.0)
        one = np.ones(len(self.kind))

        def param(x: np.ndarray) -> np.ndarray:
            return np.where(cap, x, one)

        rise = smoothstep(tau / param(self.capture_s))
        fall = smoothstep((tau - param(self.capture_s)) / param(self.recover_s))
        env = np.where(on, rise * (1.0 - fall), 0.0)
        eph = 1.0 + (param(self.eph_gain) - 1.0) * env
        return {"satellites": 1.0 - (1.0 - param(self.sat_share)) * env, "eph": eph, "epv": eph.copy(),
                "speed_acc": 1.0 + (param(self.speed_acc_gain) - 1.0) * env,
                "noise": 1.0 + np.where(on, np.where(cap, self.noise_rise, 0.0) * rise, 0.0),
                "fix_lost": on & (tau < np.where(cap, self.lock_loss_s, 0.0))}


def inject_fixes(attack: AttackBatch, tau: np.ndarray, pos: np.ndarray, vel: np.ndarray, rate_hz: float):
    """Recorded fixes spoofed by ``attack`` (one flight): ``attack.apply`` at each fix time tau
    (s on the attack's clock, (n,)) on the fixes pos, vel (n, 3), their history the recorded
    fixes (replay and freeze read it); ``rate_hz``: the fixes' rate, for a replay's delay.
    Returns (pos, vel, label (n,) bool, d_pos (n, 3))."""
    n = len(tau)
    history = torch.as_tensor(np.c_[pos, vel])[None]
    out_p, out_v = np.array(pos, dtype=float), np.array(vel, dtype=float)
    label = np.zeros(n, dtype=bool)
    d_pos = np.zeros((n, 3))
    for j in range(n):
        p, v, active, d, _ = attack.apply(float(tau[j]), j, torch.tensor(pos[j:j + 1]),
                                          torch.tensor(vel[j:j + 1]), history, rate_hz)
        out_p[j], out_v[j] = p[0].numpy(), v[0].numpy()
        label[j], d_pos[j] = bool(active[0]), d[0]
    return out_p, out_v, label, d_pos


def concat_attacks(parts: list[AttackBatch]) -> AttackBatch:
    """The flights of several ``AttackBatch`` in one, in order (each flight keeps its kind)."""
    return AttackBatch(*(np.concatenate([getattr(p, f.name) for p in parts])
                         for f in dataclasses.fields(AttackBatch)))


def sample_attacks(gens: list[np.random.Generator], cfg: AttackConfig, attacked: np.ndarray,
                   duration: float) -> AttackBatch:
    """Draw each flight's attack from its own generator (all flights draw, so the stream
    position does not depend on whether a flight is attacked)."""
    B = len(gens)
    out = {k: np.full(B, np.nan) for k in ("onset", "end", "magnitude", "rate", "frequency", "period", "delay",
                                           "accel", "capture_s", "lock_loss_s", *CAPTURE_RECEIVER)}
    step = np.zeros(B, dtype=bool)
    axes = np.array([""] * B, dtype=object)
    kinds = np.array(["none"] * B, dtype=object)
    direction = np.zeros((B, 3))
    attacked = np.asarray(attacked, dtype=bool) & (cfg.kind != "none")
    for b, rng in enumerate(gens):
        # a mixed attack draws the flight's kind first; a single kind draws nothing for it
        kind = cfg.mix[int(rng.integers(len(cfg.mix)))] if cfg.kind == MIX else cfg.kind
        ranges = cfg.ranges(kind)
        onset = rng.uniform(*cfg.onset)
        dur = rng.uniform(*ranges["duration"])
        vals = {k: rng.uniform(*ranges[k]) for k in ("magnitude", "rate", "frequency", "period", "delay")}
        choices = _HORIZONTAL if kind in HORIZONTAL_KINDS else _SUBSETS
        ax = cfg.axes if cfg.axes is not None else choices[int(rng.integers(len(choices)))]
        n = rng.standard_normal(3)
        # the parameters only drift and capture have, drawn after the others and only for them, so
        # every other kind draws exactly what it drew before they existed
        if kind == "drift":
            vals["accel"] = rng.uniform(*ranges["accel"])
            drawn = bool(rng.random() < 0.5)
            step_b = drawn if cfg.onset_step is None else bool(cfg.onset_step)
        elif kind == STEALTH:                          # the black box's acceleration
            vals["accel"] = rng.uniform(*ranges["accel"])
        elif kind == "capture":
            vals["capture_s"] = rng.uniform(*ranges["capture_s"])
            vals["lock_loss_s"] = rng.uniform(*ranges["lock_loss_s"])
            vals.update({k: rng.uniform(*r) for k, r in CAPTURE_RECEIVER.items()})
        if not attacked[b]:
            continue
        if kind == "drift":
            step[b] = step_b
        sel = np.array(["xyz"[i] in ax for i in range(3)])
        vec = np.where(sel, n, 0.0)
        direction[b] = vec / np.linalg.norm(vec)
        axes[b] = ax
        kinds[b] = kind
        out["onset"][b] = onset
        out["end"][b] = min(onset + dur, duration + 1e-9)
        for k, v in vals.items():
            out[k][b] = v
    return AttackBatch(kind=kinds, attacked=attacked, axes=axes, direction=direction, onset_step=step, **out)
