"""A step test on the GPS innovations that normalises itself on each flight (``glr``).

A spoof begins with a step: a bias moves the fix without the velocity, a consistent drift
switched on at once moves the velocity without the IMU seeing an acceleration, a receiver's
capture moves both within a second or two. The filter's innovation (the fix minus what the
IMU predicted) shows the step until the filter has absorbed it; the receiver's and the IMU's
slow errors change the innovation's mean too, but not in a step. The statistic is the
generalised likelihood ratio for a step in the innovation's mean at several scales: for each
window ``M`` of ``windows`` (seconds), the mean raw innovation over the last M seconds minus
its mean over the ``reference_s`` seconds before them,

    d_M(t) = mean r(t - M, t]  -  mean r(t - M - reference_s, t - M],

for four groups of components: horizontal position, horizontal velocity, the vertical pair
(position and velocity) of the innovation, and the receiver's own consistency: its horizontal
position change since the previous fix minus its mean velocity over the interval, which a
position step without the matching velocity (a bias) breaks at once while a real receiver keeps
it within centimetres. The interval is the receiver's, a whole number of its period
(``epoch_interval``), not the stamps' difference: the stamps jitter by tens of ms on real links
and logs (a 40 ms jitter at 6 m/s reads as a 0.24 m jump). Each component of d_M is divided by its scale sigma, the
group's squares are averaged, and the score is the largest over windows and the groups named in
``groups``: about 1 on a clean flight's typical step, large at a spoof's onset. The vertical
group is left out by default: on real vehicles without a barometer in the logs it fires on every
brisk climb (a return-to-launch's 90 against about 50 for the largest horizontal step of the
same clean flights), and spoofers move the horizontal fix.

The raw innovation, not the whitened one: a receiver under capture inflates its own accuracy
estimates, and a test whitened by them is normalised away by the very numbers the attacker
moves. The scales come from the data instead:

- ``fit`` learns prior scales from training flights (their clean steps in the air): a robust
  standard deviation (1.4826 x the median absolute deviation) of each component of each d_M;
- each flight then normalises itself. Until it has ``warm_s`` seconds in the air, the scales
  are the prior's times ``adapt`` (the noisiest vehicle the test allows: a large spoof is still
  seen); with a vehicle profile (``vehicle_``, written by ``quadformer calibrate`` from the
  vehicle's own clean flights) the prior is the vehicle's and is used as it is from take-off.
  From ``warm_s`` to ``calib_min_s`` seconds in the air (the warm-up) the scales are the flight's
  own robust standard deviations so far, widened by their extra sampling error against what
  ``calib_min_s`` seconds give (``flight_scales.warmup_widening``: a scale from a few seconds is
  uncertain, the more so for the long windows, of which a few seconds hold fewer independent
  values), never
  below the prior (a few seconds may show a flight noisier than the trained vehicles, not
  quieter: a hover's calm before the first manoeuvre is not the vehicle's noise) and at most
  ``adapt`` times it: a spoof begun early in a flight is judged against at most the trained
  vehicles' noise, not ten times it. From ``calib_min_s`` on, the scales
  are the robust standard deviations of the flight's own d_M over its steps in the air so far,
  up to its first ``calib_s`` seconds in the air (then frozen), refreshed every ``refresh_s``
  seconds of data; each is kept within ``adapt`` times the prior either way. The robust std is
  the ``quantile`` (0.75) of the absolute deviation, as a normal variable's: it follows a
  vehicle's heavier tails better than the median does and still ignores a quarter of the steps.
  A step whose score is above ``learn_below`` (25, about 5 standard deviations) is not learned
  from, so a spoof's onset inside the calibration does not teach the scale; the bound keeps
  anything else (a spoof present from take-off, a noisy flight) from teaching a scale more than
  ``adapt`` times the prior; a consistent drift present from take-off leaves the innovations as a
  clean flight's.

"In the air" is the optional ``in_air`` column of the rows (1 airborne, 0 not: a log's flight
phase, the live vehicle's); without it every step is. Time is the ``t`` column. The online
stream (``stream``) computes the same scores step by step (to 1e-9) from a bounded buffer of
the last ``max(windows) + reference_s`` seconds and the calibration's ``calib_s`` seconds.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping

import numpy as np
import pandas as pd

from quadformer.detectors.base import Detector, check_residues, flight_slices
from quadformer.detectors.flight_scales import EDGE, TINY, FlightCalibration, robust_scale
from quadformer.detectors.registry import register
from quadformer.detectors.streams import DetectorStream, StreamStep

#: the groups of the raw GPS innovation the step test reads
GROUPS = (("res_gps_r_px", "res_gps_r_py"), ("res_gps_r_vx", "res_gps_r_vy"), ("res_gps_r_pz", "res_gps_r_vz"))
#: the fix as received, for the receiver's consistency (position change against velocity)
FIX = ("gps_pos_x", "gps_pos_y", "gps_vel_x", "gps_vel_y")
INPUTS = tuple(c for g in GROUPS for c in g) + FIX
WIDTH = 8                 # components per window: the six innovations and the consistency pair
#: the four groups' names, in the order of their component pairs
GROUP_NAMES = ("position", "velocity", "vertical", "consistency")
AIR = "in_air"
PERIOD_FIXES = 50         # intervals before a fix whose median is the receiver's period
PERIOD_MIN = 5            # intervals needed before the period is used
SNAP = 0.5               # periods an interval may differ from a whole number of them to be snapped


def _check_settings(det: "StepGLR") -> None:
    w = det.windows
    if not (isinstance(w, (tuple, list)) and w and all(isinstance(v, (int, float)) and v > 0 for v in w)):
        raise ValueError(f"glr: windows must be positive seconds, got {w!r}")
    for name in ("reference_s", "calib_s", "refresh_s", "adapt", "learn_below"):
        v = getattr(det, name)
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ValueError(f"glr: {name} must be a positive number, got {v!r}")
    if not (isinstance(det.calib_min_s, (int, float)) and 0 <= det.calib_min_s <= det.calib_s):
        raise ValueError(f"glr: calib_min_s must be from 0 to calib_s ({det.calib_s!r}), got {det.calib_min_s!r}")
    unknown = set(det.groups) - set(GROUP_NAMES)
    if unknown or not det.groups:
        raise ValueError(f"glr: groups must name some of {', '.join(GROUP_NAMES)}, got {det.groups!r}")
    if det.adapt < 1:
        raise ValueError(f"glr: adapt must be at least 1, got {det.adapt!r}")
    warm = getattr(det, "warm_s", det.calib_min_s)
    if not (isinstance(warm, (int, float)) and 0 <= warm <= det.calib_min_s):
        raise ValueError(f"glr: warm_s must be from 0 to calib_min_s ({det.calib_min_s!r}), got {warm!r}")


def epoch_interval(dt: float, recent) -> float:
    """The receiver's interval between two fixes stamped ``dt`` apart: a whole number of its period
    (the median of the ``recent`` intervals, at least ``PERIOD_MIN`` of them), where ``dt`` is
    within ``SNAP`` periods of one; else ``dt`` as stamped. A receiver measures its fixes at exact
    epochs; the autopilot stamps them when it reads them, tens of ms late and jittering, and a
    test of the position change against velocity x interval reads speed x jitter as a jump."""
    if len(recent) < PERIOD_MIN:
        return dt
    period = float(np.median(np.asarray(recent)))
    m = max(1, round(dt / period)) if period > 0 else 0
    return m * period if m and abs(dt - m * period) <= SNAP * period else dt


def consistency(t: np.ndarray, fix: np.ndarray) -> np.ndarray:
    """The receiver's horizontal consistency at each fix of one flight (steps, 2): position change
    since the previous fix minus the mean of the two velocities times the interval between their
    epochs (``epoch_interval`` over the ``PERIOD_FIXES`` intervals before; 0 at the first)."""
    out = np.zeros((len(t), 2))
    if len(t) > 1:
        dt = np.diff(t)
        dt_e = np.array([epoch_interval(d, dt[max(0, k - PERIOD_FIXES):k]) for k, d in enumerate(dt)])
        out[1:] = np.diff(fix[:, :2], axis=0) - 0.5 * (fix[1:, 2:] + fix[:-1, 2:]) * dt_e[:, None]
    return out


def step_features(t: np.ndarray, x: np.ndarray, windows, reference_s: float) -> np.ndarray:
    """d_M of one flight, (steps, windows x WIDTH): for each window (in order) the six raw
    innovations and the two consistency components (``x``: the ``INPUTS`` columns; the consistency
    computed here) of the mean over (t - M, t] minus the mean over the reference before it; NaN
    where the reference holds less than half its length of data."""
    T = len(t)
    out = np.full((T, len(windows) * WIDTH), np.nan)
    if T == 0:
        return out
    x = np.hstack([x[:, :6], consistency(t, x[:, 6:])])
    c = np.vstack([np.zeros((1, x.shape[1])), np.cumsum(x, axis=0)])
    k = np.arange(T)
    for j, M in enumerate(windows):
        lo = np.searchsorted(t, t - M + EDGE, side="left")
        lo2 = np.searchsorted(t, t - M - reference_s + EDGE, side="left")
        na, nb = (k + 1 - lo), (lo - lo2)
        ok = (nb > 0) & (t[0] <= t - M - 0.5 * reference_s + EDGE)
        a = (c[k + 1] - c[lo]) / na[:, None]
        b = (c[lo] - c[lo2]) / np.where(nb > 0, nb, 1)[:, None]
        out[:, WIDTH * j:WIDTH * (j + 1)] = np.where(ok[:, None], a - b, np.nan)
    return out


def _score(d: np.ndarray, scale: np.ndarray, n_windows: int, use: np.ndarray) -> float:
    z = np.nan_to_num(d / scale) ** 2
    return float(z.reshape(n_windows, WIDTH // 2, 2).mean(axis=2)[:, use].max())


@register("glr")
class StepGLR(Detector):
    """The self-normalising step test on the raw GPS innovations (see the module text)."""

    param_grid = {"reference_s": [2.0, 3.0, 5.0]}

    def __init__(self, windows: tuple[float, ...] = (0.2, 0.5, 1.0, 2.0, 4.0), reference_s: float = 3.0,
                 calib_s: float = 60.0, calib_min_s: float = 20.0, refresh_s: float = 1.0,
                 adapt: float = 10.0, quantile: float = 0.75, track_s: float | None = None,
                 guard_s: float = 10.0, groups: tuple[str, ...] = ("position", "velocity", "consistency"),
                 learn_below: float = 25.0, warm_s: float = 2.0) -> None:
        self.windows = tuple(windows)
        self.reference_s = reference_s
        self.calib_s = calib_s
        self.calib_min_s = calib_min_s
        self.refresh_s = refresh_s
        self.adapt = adapt
        self.quantile = quantile
        self.track_s = track_s
        self.guard_s = guard_s
        self.groups = tuple(groups)
        self.learn_below = learn_below
        self.warm_s = warm_s

    # -- fitting ------------------------------------------------------------------------
    def _features(self, X: pd.DataFrame) -> tuple[list[tuple[np.ndarray, np.ndarray]], np.ndarray, np.ndarray]:
        values = check_residues(X, list(INPUTS))
        if "t" not in X.columns:
            raise ValueError("glr: the rows need a time column t (seconds)")
        t = X["t"].to_numpy(dtype=float)
        air = self._air(X)
        d = np.full((len(X), len(self.windows) * WIDTH), np.nan)
        slices = flight_slices(X)
        for _, idx in slices:
            if np.any(np.diff(t[idx]) < 0):
                raise ValueError("glr: each flight's rows must be in time order")
            d[idx] = step_features(t[idx], values[idx], self.windows, self.reference_s)
        return slices, d, air

    @staticmethod
    def _air(X: pd.DataFrame) -> np.ndarray:
        if AIR not in X.columns:
            return np.ones(len(X), dtype=bool)
        a = X[AIR].to_numpy(dtype=float)
        return np.isfinite(a) & (a > 0.5)

    def fit(self, X: pd.DataFrame, y: np.ndarray | None = None) -> "StepGLR":
        _check_settings(self)
        _, d, air = self._features(X)
        keep = air.copy()
        if y is not None:
            keep &= np.asarray(y) == 0
        elif "label" in X.columns:
            keep &= X["label"].to_numpy() == 0
        scale = robust_scale(d[keep], self.quantile)
        if not np.isfinite(scale).all():
            need = self.reference_s + max(self.windows)
            raise ValueError("glr: too few clean steps in the air to fit its scales "
                             f"({int(keep.sum())} steps; a flight needs more than {need:g} s)")
        self.scale_ = np.maximum(scale, TINY)
        dt = np.diff(X["t"].to_numpy(dtype=float))
        dt = dt[dt > 0]
        self.rate_hz_ = float(1.0 / np.median(dt)) if len(dt) else 10.0
        self.features_ = list(INPUTS)
        self.fitted_ = True
        return self

    # -- scoring ------------------------------------------------------------------------
    def decision_function(self, X: pd.DataFrame) -> np.ndarray:
        self.check_fitted()
        slices, d, air = self._features(X)
        t = X["t"].to_numpy(dtype=float)
        out = np.zeros(len(X))
        nw = len(self.windows)
        use = self._use()
        for _, idx in slices:
            cal = FlightCalibration(self)
            for k in idx:
                out[k] = _score(d[k], cal.scales(t[k]), nw, use)
                cal.add(t[k], d[k], bool(air[k]), out[k])
        return out

    def _use(self) -> np.ndarray:
        return np.array([g in self.groups for g in GROUP_NAMES])

    def stream(self, n_flights: int = 1) -> "GLRStream":
        return GLRStream(self, n_flights)

    def load_state(self, state: dict) -> None:
        super().load_state(state)
        self.scale_ = np.asarray(self.scale_, dtype=float)


class GLRStream(DetectorStream):
    """The step test online: per flight, the last ``max(windows) + reference_s`` seconds of raw
    innovations and the calibration. ``update`` takes the six raw innovation columns (a mapping
    or an array in ``features_`` order) and, in a mapping, the time ``t`` (s) and optionally
    ``in_air``; without ``t`` the steps are taken to come at the rate of the training data
    (``rate_hz_``), the first at 0."""

    def __init__(self, detector: StepGLR, n_flights: int):
        super().__init__(detector, n_flights)
        self.span = max(detector.windows) + detector.reference_s
        self.buf: list[deque] = [deque() for _ in range(self.n)]
        self.first_t = [math.nan] * self.n
        self.cal = [FlightCalibration(detector) for _ in range(self.n)]
        self.steps = 0
        self.use = detector._use()
        self.prev: list[tuple[float, np.ndarray] | None] = [None] * self.n
        self.intervals: list[deque] = [deque(maxlen=PERIOD_FIXES) for _ in range(self.n)]

    def update(self, residues) -> StreamStep:
        x = self._matrix(residues)
        if isinstance(residues, Mapping) and "t" in residues:
            t = np.broadcast_to(np.asarray(residues["t"], dtype=float).reshape(-1), (self.n,))
        else:
            t = np.full(self.n, self.steps / float(getattr(self.detector, "rate_hz_", 10.0)))
        self.steps += 1
        air = np.ones(self.n, dtype=bool)
        if isinstance(residues, Mapping) and AIR in residues:
            a = np.broadcast_to(np.asarray(residues[AIR], dtype=float).reshape(-1), (self.n,))
            air = np.isfinite(a) & (a > 0.5)
        det = self.detector
        score = np.zeros(self.n)
        for i in range(self.n):
            ti = float(t[i])
            if not math.isfinite(ti):
                raise ValueError(f"glr: a non-finite time t ({ti!r})")
            buf = self.buf[i]
            if buf and ti < buf[-1][0]:
                raise ValueError(f"glr: time went back (t {ti!r} after {buf[-1][0]!r})")
            if math.isnan(self.first_t[i]):
                self.first_t[i] = ti
            e = np.zeros(2)
            if self.prev[i] is not None:
                tp, fp = self.prev[i]
                dt_e = epoch_interval(ti - tp, self.intervals[i])
                self.intervals[i].append(ti - tp)
                e = (x[i, 6:8] - fp[:2]) - 0.5 * (x[i, 8:10] + fp[2:]) * dt_e
            self.prev[i] = (ti, x[i, 6:10].copy())
            buf.append((ti, np.concatenate([x[i, :6], e])))
            while buf and buf[0][0] <= ti - self.span - 1e-9:
                buf.popleft()
            d = self._features(i, ti)
            score[i] = _score(d, self.cal[i].scales(ti), len(det.windows), self.use)
            self.cal[i].add(ti, d, bool(air[i]), score[i])
        thr = getattr(det, "threshold_", None)
        alarm = score > thr if thr is not None else np.zeros(self.n, dtype=bool)
        return StreamStep(score, alarm, None, None)

    def resume(self, before: "GLRStream") -> None:
        """Go on from ``before``, the same flights' stream until now (the live monitor restarting
        its filter in the air, e.g. with the receiver's latency found): each flight whose
        calibration there was done keeps its scales as its prior, trusted from the start (a vehicle
        profile's rule), and calibrates itself afresh on the new residues from ``calib_min_s``
        seconds in the air on; its window and reference start empty."""
        if before.n != self.n or before.detector.windows != self.detector.windows:
            raise ValueError("glr: a stream resumes one of the same flights and windows")
        for i in range(self.n):
            carried = before.cal[i].calibrated
            if carried is not None:
                self.cal[i] = FlightCalibration(self.detector, prior=carried)

    def _features(self, i: int, ti: float) -> np.ndarray:
        det = self.detector
        buf = self.buf[i]
        ts = np.array([b[0] for b in buf])
        xs = np.array([b[1] for b in buf])
        k = len(ts) - 1
        out = np.full(len(det.windows) * WIDTH, np.nan)
        for j, M in enumerate(det.windows):
            lo = int(np.searchsorted(ts, ti - M + EDGE, side="left"))
            lo2 = int(np.searchsorted(ts, ti - M - det.reference_s + EDGE, side="left"))
            if lo > lo2 and self.first_t[i] <= ti - M - 0.5 * det.reference_s + EDGE:
                out[WIDTH * j:WIDTH * (j + 1)] = xs[lo:k + 1].mean(axis=0) - xs[lo2:lo].mean(axis=0)
        return out
