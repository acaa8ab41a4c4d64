"""An attacker who knows the detector: each spoofed fix chosen as the flight goes.

The offset runs along each flight's horizontal direction u, consistent: the fix's position is
the truth plus ``s u`` and its velocity the truth's plus ``s' u``, with s' the speed the attacker
moves its offset at this GPS step (at most ``rate`` m/s either way). The vehicle, flying on its
estimate, is steered by -s u.

- ``white`` box: the attacker runs the detector's own online stream (``detector.stream``) on the
  fix it is about to send. The residues of a candidate fix are what the filter would make of
  it, computed by the closed loop on copies of the filter's state (``rows``: the attacker knows
  the filter and the vehicle's dynamics). At each GPS step it sends the fastest push toward its
  goal whose score stays at or under ``margin`` x threshold: a grid of speeds over
  [-rate, rate], then bisection between the fastest that passes and the next that does not.
  Where none passes, it sends the speed of the lowest score it finds (a golden-section search
  about the grid's lowest: pulling back or holding to hide). After the step, its stream takes
  the residues of the fix sent, as the detector's does. It knows the fix it sends (it sits
  where the fix is made), not what the receiver's noise will be at the next one: a score kept
  at the bound can be pushed over it by the next fix's noise, which ``margin`` leaves room for.
- ``grey`` box: the white box's search, run on a surrogate: the same method with its default
  parameters, fitted and calibrated on the attacker's own flights (another vehicle, other noise
  draws), not on the vehicle's. It knows the method, not the calibration; what it achieves is
  judged by the vehicle's own detector.
- ``black`` box: no score; the offset accelerates in at ``accel`` up to ``rate`` m/s, the
  slow drift an attacker without access to the detector would choose.

With a plan (``plan_accel`` a) the white and grey boxes follow it under their score: the push's
speed grows at most a m/s each second, from the speed last sent. At each GPS step the plan's speed
is tried first and sent when its score is at or under the bound; else the search above runs on
speeds up to it. A slow plan keeps the score low where the fastest push keeps it at the bound: an
attacker that rehearses plans on its own flights (``experiments.stealth.rehearse``) picks the one
that goes farthest unseen, the fastest push (no plan) among them.

With ``headings`` H > 1 the white and grey boxes search across the track too: at each GPS step the
speed grid on each of H axes (the direction turned by pi h / H about the vertical, both ways), the
push that leaves the fix farthest from the truth with the score at or under the bound (ties to
the direction at its top speed), then bisection outward on that axis; where none passes, the
lowest score found. The offset is then a horizontal vector; H times the probes of one axis.

What the attacker achieves is measured on the vehicle: its true position's deviation from the
mission until the detector's first alarm (``experiments.stealth``).
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Mapping

import numpy as np
import torch

from quadformer.attacks._attacks import AttackBatch
from quadformer.config import KNOWLEDGE, STEALTH

#: speeds tried at each GPS step, as shares of the attacker's top speed, then bisection steps
GRID = np.linspace(-1.0, 1.0, 9)
REFINE = 4


class StealthyAttacker:
    """The stealthy attack of a batch's flights (those of ``attack`` whose kind is ``stealthy``).

    stream: the online stream over the batch of the detector the attacker runs (the vehicle's own
    in the white box, its surrogate in the grey box; None for black box); threshold: that
    detector's alarm threshold."""

    def __init__(self, attack: AttackBatch, knowledge: str, margin: float, rate_hz: float, stream=None,
                 threshold: float | None = None, headings: int = 1, plan_accel: float | None = None):
        if knowledge not in KNOWLEDGE:
            raise ValueError(f"knowledge: {knowledge!r}; choose from {', '.join(KNOWLEDGE)}")
        if not 0.0 < margin <= 1.0:
            raise ValueError(f"margin: must be in (0, 1], got {margin!r}")
        if knowledge != "black" and (stream is None or threshold is None or not np.isfinite(threshold)):
            raise ValueError(f"a {knowledge}-box attacker needs a detector's stream and its threshold")
        self.attack, self.knowledge, self.margin = attack, knowledge, float(margin)
        self.dt = 1.0 / float(rate_hz)
        self.stream, self.threshold = stream, threshold
        self.mine = np.asarray(attack.attacked, bool) & (np.asarray(attack.kind) == STEALTH)
        B = len(self.mine)
        if not (isinstance(headings, int) and headings >= 1):
            raise ValueError(f"headings: a whole number of at least 1, got {headings!r}")
        self.headings = 1 if knowledge == "black" else headings
        if plan_accel is not None and not (knowledge != "black" and self.headings == 1 and np.isfinite(plan_accel)
                                           and plan_accel > 0):
            raise ValueError(f"plan_accel: a positive acceleration for a white or grey box along one heading, "
                             f"got {plan_accel!r}")
        self.plan_accel = None if plan_accel is None else float(plan_accel)
        self.offset = np.zeros(B)          # m along u
        self.speed = np.zeros(B)           # m/s along u, at the last fix
        self.offset_h = np.zeros((B, 3))   # with several headings: the offset (m), ENU
        # what a trial copy of the stream shares with it: the detector and its model (deepcopy's memo)
        det = getattr(stream, "detector", None)
        self._shared = {} if det is None else {id(det): det, **{id(v): v for v in vars(det).values()}}

    @property
    def bound(self) -> float:
        return self.margin * float(self.threshold)

    def active(self, t: float) -> np.ndarray:
        return self.mine & self.attack.window(t)

    def fixes(self, t: float, pos: torch.Tensor, vel: torch.Tensor,
              rows: Callable[[torch.Tensor, torch.Tensor], Mapping[str, np.ndarray]] | None = None):
        """The fixes sent at time t for the honest ones pos, vel (B, 3): (pos, vel, active (B,) bool,
        d_pos (B, 3)). ``rows(pos, vel)``: the residue columns the filter would make of candidate
        fixes, its state left as it is (white box)."""
        active = self.active(t)
        B = len(active)
        if not active.any():
            return pos, vel, active, np.zeros((B, 3))
        cap = np.where(active, self.attack.rate, 0.0)
        if self.knowledge != "black" and rows is None:
            raise ValueError(f"a {self.knowledge}-box attacker scores its candidate fixes: pass rows")
        if self.headings > 1:
            v = np.where(active[:, None], self._headings(pos, vel, cap, rows), 0.0)
            self.offset_h = np.where(active[:, None], self.offset_h + v * self.dt, self.offset_h)
            d_pos = np.where(active[:, None], self.offset_h, 0.0)
            return pos + torch.from_numpy(d_pos), vel + torch.from_numpy(v), active, d_pos
        if self.knowledge == "black":
            speed = np.minimum(self.speed + np.where(active, self.attack.accel, 0.0) * self.dt, cap)
        else:
            top = cap if self.plan_accel is None else np.minimum(cap, self.speed + self.plan_accel * self.dt)
            speed = self._white(pos, vel, cap, rows, np.where(active, top, 0.0))
        speed = np.where(active, speed, 0.0)
        self.offset = np.where(active, self.offset + speed * self.dt, self.offset)
        self.speed = speed
        u = self.attack.direction
        d_pos = np.where(active[:, None], self.offset[:, None] * u, 0.0)
        d_vel = np.where(active[:, None], speed[:, None] * u, 0.0)
        return pos + torch.from_numpy(d_pos), vel + torch.from_numpy(d_vel), active, d_pos

    def observe(self, columns: Mapping[str, np.ndarray]) -> None:
        """The residues of the fixes sent: the attacker's stream steps as the detector's does."""
        if self.stream is not None:
            self.stream.update(columns)

    # -- the white box ---------------------------------------------------------------------------
    def _score(self, pos, vel, speed, rows) -> np.ndarray:
        u = self.attack.direction
        off = (self.offset + speed * self.dt)[:, None] * u
        cols = rows(pos + torch.from_numpy(off), vel + torch.from_numpy(speed[:, None] * u))
        s = np.asarray(self._trial().update(cols).score, dtype=float)
        return np.where(np.isfinite(s), s, np.inf)

    # -- several headings ------------------------------------------------------------------------
    def _axes(self) -> np.ndarray:
        """The searched axes (H, B, 3): the attack's direction turned by pi h / H about the vertical."""
        u = np.asarray(self.attack.direction, dtype=float)
        out = []
        for h in range(self.headings):
            a = np.pi * h / self.headings
            c, s = np.cos(a), np.sin(a)
            out.append(np.stack([c * u[:, 0] - s * u[:, 1], s * u[:, 0] + c * u[:, 1], np.zeros(len(u))], axis=1))
        return np.stack(out)

    def _score_v(self, pos, vel, v: np.ndarray, rows) -> np.ndarray:
        off = self.offset_h + v * self.dt
        cols = rows(pos + torch.from_numpy(off), vel + torch.from_numpy(v))
        s = np.asarray(self._trial().update(cols).score, dtype=float)
        return np.where(np.isfinite(s), s, np.inf)

    def _headings(self, pos, vel, cap, rows) -> np.ndarray:
        """The push (B, 3) that moves the fix farthest from the truth with the score at or under the
        bound: the speed grid on each axis (both ways), then bisection outward on the best one's
        axis; where none passes, the lowest score found (pulling back or holding to hide)."""
        bound, axes = self.bound, self._axes()
        B = len(cap)
        best_v, best_far = np.zeros((B, 3)), np.full(B, -np.inf)
        low_v, low_s = np.zeros((B, 3)), np.full(B, np.inf)
        best_h, best_f = np.zeros(B, dtype=int), np.zeros(B)
        for h in range(self.headings):
            for f in GRID[::-1]:           # ties go to the attack's own direction, at its top speed
                v = f * cap[:, None] * axes[h]
                sc = self._score_v(pos, vel, v, rows)
                far = np.linalg.norm((self.offset_h + v * self.dt)[:, :2], axis=1)
                better = (sc <= bound) & (far > best_far + 1e-12)
                best_v, best_far = np.where(better[:, None], v, best_v), np.where(better, far, best_far)
                best_h, best_f = np.where(better, h, best_h), np.where(better, f, best_f)
                lower = sc < low_s
                low_v, low_s = np.where(lower[:, None], v, low_v), np.where(lower, sc, low_s)
        found = np.isfinite(best_far)
        # bisection outward on the chosen axis: between the best grid speed and the next one beyond it
        step = GRID[1] - GRID[0]
        lo = best_f
        hi = np.clip(best_f + np.sign(best_f) * step, -1.0, 1.0)
        refine = found & (np.abs(hi) > np.abs(lo))
        ax = axes[best_h, np.arange(B)]
        for _ in range(REFINE if refine.any() else 0):
            mid = 0.5 * (lo + hi)
            good = self._score_v(pos, vel, np.where(refine, mid, lo)[:, None] * cap[:, None] * ax, rows) <= bound
            lo, hi = np.where(refine & good, mid, lo), np.where(refine & ~good, mid, hi)
        chosen = lo[:, None] * cap[:, None] * ax
        return np.where(found[:, None], chosen, low_v)

    def _trial(self):
        """A copy of the stream to try a fix on, sharing the detector (its model) with the original
        (a fresh memo each time: deepcopy fills it with the copies it makes)."""
        return copy.deepcopy(self.stream, dict(self._shared))

    def _white(self, pos, vel, cap, rows, top) -> np.ndarray:
        """The fastest speed in [-cap, top] whose score is at or under the bound: ``top`` first, then
        the grid over the range and bisection; where none passes, the speed of the lowest score."""
        bound = self.bound
        top_score = self._score(pos, vel, top, rows)
        if (top_score <= bound).all():
            return top

        def at(f):                               # a grid share in [-1, 1] as a speed in [-cap, top]
            f = np.asarray(f)
            return f * cap if self.plan_accel is None else -cap + 0.5 * (f + 1.0) * (top + cap)

        scores = np.stack([self._score(pos, vel, at(f), rows) for f in GRID[:-1]] + [top_score])    # (G, B)
        ok = scores <= bound
        G = len(GRID)
        best = np.where(ok.any(0), G - 1 - np.argmax(ok[::-1], 0), np.argmin(scores, 0))
        lo = at(GRID[best])
        refine = ok.any(0) & (best < G - 1)
        hi = at(GRID[np.minimum(best + 1, G - 1)])
        for _ in range(REFINE if refine.any() else 0):
            mid = 0.5 * (lo + hi)
            good = self._score(pos, vel, np.where(refine, mid, lo), rows) <= bound
            lo = np.where(refine & good, mid, lo)
            hi = np.where(refine & ~good, mid, hi)
        caught = ~ok.any(0) & (cap > 0)
        if caught.any():
            lo = np.where(caught, self._lowest(pos, vel, at, rows, np.argmin(scores, 0)), lo)
        return lo

    def _lowest(self, pos, vel, at, rows, best: np.ndarray) -> np.ndarray:
        """The speed of the lowest score between the grid's neighbours of its lowest, ``best``
        (golden-section search, ``REFINE`` + 2 steps); ``at`` maps a grid share to a speed."""
        G, phi = len(GRID), (np.sqrt(5.0) - 1.0) / 2.0
        a, b = at(GRID[np.maximum(best - 1, 0)]), at(GRID[np.minimum(best + 1, G - 1)])
        c, d = b - phi * (b - a), a + phi * (b - a)
        fc, fd = self._score(pos, vel, c, rows), self._score(pos, vel, d, rows)
        for _ in range(REFINE + 2):
            left = fc <= fd                       # the lowest lies in [a, d], else in [c, b]
            a, b = np.where(left, a, c), np.where(left, d, b)
            keep, f_keep = np.where(left, c, d), np.where(left, fc, fd)
            new = np.where(left, b - phi * (b - a), a + phi * (b - a))
            f_new = self._score(pos, vel, new, rows)
            c, fc = np.where(left, new, keep), np.where(left, f_new, f_keep)
            d, fd = np.where(left, keep, new), np.where(left, f_keep, f_new)
        return np.where(fc <= fd, c, d)
