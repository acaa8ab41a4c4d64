"""A flight's own noise scales, for a test that normalises itself on each flight (``glr``): the
robust standard deviation of a set of steps, its widening while few seconds back it (the
warm-up), and the calibration that follows one flight step by step (``FlightCalibration``; the
rules are in ``detectors.glr``'s module text)."""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from scipy.special import ndtri

__all__ = ["EDGE", "TINY", "FlightCalibration", "robust_scale", "warmup_widening"]

TINY = 1e-6               # a scale is never below this (m or m/s)
EDGE = 1e-6               # s: a step exactly M seconds old is outside the window, whatever the rounding of t
WARM_SIGMAS = 3.0         # the warm-up widens a scale by this many of its estimate's standard errors
WARM_SPACING_S = 0.2      # s between two windows counted as independent, beyond their length
WARM_MIN_VALUES = 10      # values a column's own scale needs in the warm-up


def warmup_widening(air_s, windows, calib_min_s: float, quantile: float) -> np.ndarray:
    """Per window, the factor a flight's own scale is widened by after ``air_s`` seconds in the
    air (one number, or one per window: the seconds its values cover), before ``calib_min_s`` (1
    from then on): 1 + ``WARM_SIGMAS`` x the estimate's relative standard error now less that at
    ``calib_min_s``. The robust std (the ``quantile`` of the absolute deviation) of n independent
    normal values has relative standard error sqrt(q (1 - q)) / (2 phi(z) z) / sqrt(n), z the normal quantile of (1 + q) / 2 (0.91 / sqrt(n)
    at q 0.75); a window of M seconds gives about one independent value every M + ``WARM_SPACING_S``
    seconds. The calibration trusts the scale from ``calib_min_s`` on; before, it is widened by
    the uncertainty it has beyond that trust, so the factor meets 1 there without a jump."""
    z = float(ndtri(0.5 + quantile / 2))
    rel = math.sqrt(quantile * (1 - quantile)) / (2 * math.exp(-0.5 * z * z) / math.sqrt(2 * math.pi) * z)
    out = []
    for M, a in zip(windows, np.broadcast_to(np.asarray(air_s, dtype=float), (len(windows),))):
        n_now = max(float(a), 1e-9) / (M + WARM_SPACING_S)
        n_trust = max(calib_min_s, 1e-9) / (M + WARM_SPACING_S)
        out.append(1.0 + WARM_SIGMAS * rel * max(0.0, 1.0 / math.sqrt(n_now) - 1.0 / math.sqrt(n_trust)))
    return np.asarray(out)


def robust_scale(d: np.ndarray, q: float = 0.5) -> np.ndarray:
    """Per column, of the finite rows: the q-quantile of the absolute deviation about the median,
    as a normal variable's std (q 0.5: 1.4826 x the median absolute deviation); NaN for a column
    without a finite row."""
    d = np.asarray(d, dtype=float)
    out = np.full(d.shape[1], np.nan)
    have = np.isfinite(d).any(axis=0)
    if have.any():
        x = d[:, have]
        dev = np.abs(x - np.nanmedian(x, axis=0))
        out[have] = _nanquantile(dev, q) / float(ndtri(0.5 + q / 2))   # the normal quantile
    return out


def _nanquantile(x: np.ndarray, q: float) -> np.ndarray:
    """``np.nanquantile(x, q, axis=0)`` (the same numbers) in one call per pattern of missing
    rows: the columns of a window share theirs (the steps before the window filled), and
    numpy's NaN-aware quantile works a column at a time."""
    nan = np.isnan(x)
    if not nan.any():
        return np.quantile(x, q, axis=0)
    out = np.full(x.shape[1], np.nan)
    patterns: dict[bytes, list[int]] = {}
    for j in range(x.shape[1]):
        patterns.setdefault(nan[:, j].tobytes(), []).append(j)
    for cols in patterns.values():
        rows = ~nan[:, cols[0]]
        if rows.any():
            out[cols] = np.quantile(x[np.ix_(rows, cols)], q, axis=0)
    return out


class FlightCalibration:
    """One flight's self-normalisation (``detectors.glr``'s module text), fed step by step:
    ``scales(t)`` before the step's score, ``add(t, d, in_air, score)`` after it. ``det``: the
    detector whose settings and trained scales (``scale_``, one per component of each of its
    ``windows``, window by window) it follows; ``prior``: scales of the same flight calibrated
    before (``calibrated``), trusted as a vehicle profile's are, instead of the trained ones."""

    def __init__(self, det, prior: np.ndarray | None = None):
        self.det = det
        self.width = len(det.scale_) // len(det.windows)     # components per window
        self.prior = np.maximum(np.asarray(det.scale_ if prior is None else prior, dtype=float), TINY)
        # the prior is the vehicle's own (a vehicle profile: ``logs.calibration.vehicle_profile``, or
        # ``prior``: the scales this flight had calibrated before, carried over): trusted from
        # take-off; else the noisiest vehicle allowed until the warm-up begins
        self.vehicle = prior is not None or bool(getattr(det, "vehicle_", None))
        self.scale = self.prior.copy() if self.vehicle else self.prior * det.adapt
        self.rows: deque[tuple[float, np.ndarray]] = deque()   # (t, d) of steps in the air
        self.air_s = 0.0               # s of steps in the air taken so far
        self.last_t = math.nan         # the previous step's time
        self.last_air = False
        self.refreshed = -math.inf     # when the scales were last computed
        self.frozen = False

    def scales(self, t: float) -> np.ndarray:
        det = self.det
        if self.frozen or t < self.refreshed + det.refresh_s - EDGE:
            return self.scale
        warming = self.air_s < det.calib_min_s - EDGE
        if warming and (self.vehicle or self.air_s < getattr(det, "warm_s", det.calib_min_s) - EDGE):
            return self.scale
        rows = self.rows
        if det.track_s is not None:          # a trailing window, the last guard_s left out
            while rows and rows[0][0] < t - det.track_s - det.guard_s - EDGE:
                rows.popleft()
            use = [d for ti, d in rows if ti <= t - det.guard_s + EDGE]
        else:
            use = [d for _, d in rows]
        if len(use) >= 2:
            own = robust_scale(np.asarray(use), det.quantile)
            if warming:
                # each column's own scale widened for the seconds its values cover; one with fewer
                # than WARM_MIN_VALUES values keeps the noisiest vehicle's scale
                have = np.isfinite(np.asarray(use)).sum(axis=0)
                covered = (have.reshape(len(det.windows), self.width).min(axis=1) / len(use)) * self.air_s
                wide = np.repeat(warmup_widening(covered, det.windows, det.calib_min_s, det.quantile), self.width)
                own = np.where(np.isfinite(own) & (have >= WARM_MIN_VALUES), own * wide, self.prior * det.adapt)
                # a few seconds may show a flight noisier than the prior, not quieter: a hover's
                # calm before the first manoeuvre is not the vehicle's noise
                own = np.maximum(own, self.prior)
            else:
                own = np.where(np.isfinite(own), own, self.prior)
            self.scale = np.clip(own, self.prior / det.adapt, self.prior * det.adapt)
            self.refreshed = t
            if det.track_s is None and self.air_s >= det.calib_s - EDGE:
                self.frozen = True
                self.rows = deque()
        return self.scale

    @property
    def calibrated(self) -> np.ndarray | None:
        """The flight's own scales, once it has had ``calib_min_s`` seconds in the air (else None)."""
        return self.scale.copy() if self.air_s >= self.det.calib_min_s - EDGE else None

    def add(self, t: float, d: np.ndarray, in_air: bool, score: float) -> None:
        if in_air and self.last_air and math.isfinite(self.last_t):
            self.air_s += max(0.0, t - self.last_t)
        self.last_t, self.last_air = t, in_air
        if (in_air and not self.frozen and score <= self.det.learn_below
                and (self.det.track_s is not None or self.air_s <= self.det.calib_s + EDGE)):
            self.rows.append((t, d))
