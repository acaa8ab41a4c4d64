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

from quadformer.config import MIX, AttackConfig

_SUBSETS = ("x", "y", "xy", "xz", "yz", "xyz")
_HORIZONTAL = ("x", "y", "xy")


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
        raise ValueError(f"unknown attack kind {kind!r}")   # pragma: no cover - the config validates kinds


def concat_attacks(parts: list[AttackBatch]) -> AttackBatch:
    """The flights of several ``AttackBatch`` in one, in order (each flight keeps its kind)."""
    return AttackBatch(*(np.concatenate([getattr(p, f.name) for p in parts])
                         for f in dataclasses.fields(AttackBatch)))


def sample_attacks(gens: list[np.random.Generator], cfg: AttackConfig, attacked: np.ndarray,
                   duration: float) -> AttackBatch:
    """Draw each flight's attack from its own generator (all flights draw, so the stream
    position does not depend on whether a flight is attacked)."""
    B = len(gens)
    out = {k: np.full(B, np.nan) for k in ("onset", "end", "magnitude", "rate", "frequency", "period", "delay")}
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
        choices = _HORIZONTAL if kind == "ramp" else _SUBSETS
        ax = cfg.axes if cfg.axes is not None else choices[int(rng.integers(len(choices)))]
        n = rng.standard_normal(3)
        if not attacked[b]:
            continue
        sel = np.array(["xyz"[i] in ax for i in range(3)])
        vec = np.where(sel, n, 0.0)
        direction[b] = vec / np.linalg.norm(vec)
        axes[b] = ax
        kinds[b] = kind
        out["onset"][b] = onset
        out["end"][b] = min(onset + dur, duration + 1e-9)
        for k, v in vals.items():
            out[k][b] = v
    return AttackBatch(kinds, attacked, out["onset"], out["end"], axes, direction,
                       out["magnitude"], out["rate"], out["frequency"], out["period"], out["delay"])
