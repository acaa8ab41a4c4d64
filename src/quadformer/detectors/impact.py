"""Impacts: a hard landing or a crash in the accelerometer.

A vehicle that hits the ground stops against it within a few hundredths of a second: the
accelerometer's specific force jumps far above the 1 g of hover, or, when the motors stop or the
vehicle tumbles before the hit, falls towards 0 (free fall). Its GPS innovations are large for a
moment then, before the autopilot says it has landed (a crash may never say so); the flight
phase (``flight_phase.FlightPhase.impact``) makes the seconds around such an impact a transition.

``impacts(imu)`` finds them in a whole IMU frame (vectorised), ``ImpactDetector`` one sample at
a time (the live monitor); both give the same impacts. From the specific force ``f`` (columns
``ax``, ``ay``, ``az``, m/s^2, any body frame: only its magnitude counts), averaged as a vector
over the samples of the last ``window_s``, in g (9.80665 m/s^2):

- a spike: ``|f|`` more than ``impact_g`` above 1 g (default 2 g: ``|f| > 3 g``); a crash where
  it is more than ``crash_g`` above (4 g: ``|f| > 5 g``);
- a free fall: ``|f|`` below ``freefall_g`` (0.3 g) for ``freefall_s`` (0.1 s), dated at the
  sample that completes it;
- an inversion, a crash: the mean's component along the body's up axis (``az``, body FLU) below
  ``-inverted_g`` (-0.5 g) for ``inverted_s`` (0.3 s), dated likewise. A multirotor's rotors
  push along its up axis, so in flight that component is positive whatever the manoeuvre; it
  turns negative when the vehicle lies upside down, or tumbles, after losing control.

One impact is reported per ``refractory_s`` (1 s: the bounces of one hit are one impact), but a
crash after a smaller impact within it is reported too. Samples with a non-finite acceleration
are left out (a dropped sample is no impact).

Why a 50 ms mean and not each sample: a multirotor's vibration reaches the accelerometer as
spikes of single samples. On the 22 real DataFlash logs of the field set, single samples in the
air reach 8.1 g above 1 g, and a per-sample rule finds 26 and 22 impacts in the two most
vibrating flights; the 50 ms mean (three samples at 50 Hz) finds 3 and 6 there, each where the
height is back within about 1 m of the ground height; eight flights' ends stay impacts (2.0 to
3.0 g above 1 g over 50 ms, and a crash at 7.0 g), three gentler touchdowns seen in single
samples only (2.0 to 3.0 g) do not (their landed event or height dates them). The inversion
rule was added for a loss of control that the spikes miss: an Erle-Copter that flipped in the air
and came to rest upside down (`11-2-2015_112`: 4.6 g in single samples, below 3 g over 50 ms;
the innovations of its fall raised a spoofing alert in the air as it flipped). On the 22 DataFlash
logs an inversion is found in the last 2 s of six and five times within four others (one after
a hard landing the log goes on from), all Erle-Copters, never in the Pixhawk flights. Whether an
impact is a landing is the flight phase's to say: a crash anywhere, a smaller one only near the
ground (``PhaseRule.near_m``): a fixed-wing's pull-outs reach 3 g hundreds of metres up.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
import pandas as pd

G0 = 9.80665                                   # m/s^2 per g
IMU_COLUMNS = ("t", "ax", "ay", "az")          # what impacts() reads of an IMU frame
IMPACT_COLUMNS = ["t", "event", "detail", "g", "crash"]


@dataclass(frozen=True)
class ImpactRule:
    impact_g: float = 2.0       # g above 1 g of the mean specific force that is an impact (|f| > 3 g)
    crash_g: float = 4.0        # g above 1 g that is a crash: an impact wherever the vehicle is (|f| > 5 g)
    freefall_g: float = 0.3     # g, |f| below this is free fall...
    freefall_s: float = 0.1     # s, ...once it has lasted this long
    inverted_g: float = 0.5     # g, the mean's up (body z) component below minus this is upside down...
    inverted_s: float = 0.3     # s, ...a crash once it has lasted this long
    window_s: float = 0.05      # s, the specific force is the mean over the samples of the last window_s
    refractory_s: float = 1.0   # s, one impact per this long (but a crash after a smaller impact too)

    def __post_init__(self):
        for name in ("impact_g", "crash_g", "freefall_g", "freefall_s", "inverted_g", "inverted_s", "window_s",
                     "refractory_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0):
                raise ValueError(f"ImpactRule.{name} must be a finite number >= 0, got {v!r}")
        if self.impact_g <= 0:
            raise ValueError(f"ImpactRule.impact_g must be > 0, got {self.impact_g!r}")
        if self.crash_g < self.impact_g:
            raise ValueError(f"ImpactRule.crash_g ({self.crash_g!r}) must be at least impact_g ({self.impact_g!r})")
        if self.freefall_g >= 1:
            raise ValueError(f"ImpactRule.freefall_g must be below 1 g, got {self.freefall_g!r}")


@dataclass(frozen=True)
class Impact:
    """One impact: when, the mean specific force then (g), whether it is a crash, and in words
    (``crash: 7.0 g``, ``impact: 3.1 g``, ``impact: free fall 0.10 s``)."""
    t: float
    g: float
    crash: bool
    detail: str


def _spike(rule: ImpactRule, t: float, g: float) -> Impact:
    crash = g - 1.0 > rule.crash_g
    return Impact(t, g, crash, f"{'crash' if crash else 'impact'}: {g:.1f} g")


def _fall(t: float, g: float, lasted: float) -> Impact:
    return Impact(t, g, False, f"impact: free fall {lasted:.2f} s")


def _inverted(t: float, g: float, lasted: float) -> Impact:
    return Impact(t, g, True, f"crash: upside down {lasted:.2f} s")


class _Run:
    """A condition held for ``lasting`` s, one sample at a time: ``update`` gives how long it had
    held at the sample that completes the run (once per run), None otherwise."""

    def __init__(self, lasting: float):
        self.lasting = lasting
        self.since = math.nan      # s, the first sample of the current run
        self.told = False          # the current run is reported

    def update(self, holds: bool, t: float) -> float | None:
        if not holds:
            self.since, self.told = math.nan, False
            return None
        if math.isnan(self.since):
            self.since = t
        if self.told or t - self.since < self.lasting:
            return None
        self.told = True
        return t - self.since


class _Refractory:
    """The reporting rule shared by both routes: one impact per ``refractory_s``, and a crash
    after a smaller impact within it."""

    def __init__(self, refractory_s: float):
        self.refractory_s = refractory_s
        self.last = -math.inf          # s, the last impact reported
        self.last_crash = -math.inf    # s, the last crash reported

    def admit(self, imp: Impact) -> bool:
        if imp.t - self.last >= self.refractory_s or (imp.crash and imp.t - self.last_crash >= self.refractory_s):
            self.last = imp.t
            if imp.crash:
                self.last_crash = imp.t
            return True
        return False


def impacts(imu: pd.DataFrame, rule: ImpactRule = ImpactRule()) -> pd.DataFrame:
    """The impacts of an IMU frame (columns t in s, in order, and ax, ay, az in m/s^2; others are
    ignored) as events: a frame with columns t, event (``impact``), detail (in words), g (the mean
    specific force, g) and crash (bool), by time; empty when there are none."""
    missing = [c for c in IMU_COLUMNS if c not in imu.columns]
    if missing:
        raise ValueError(f"imu: columns {', '.join(missing)} missing (has {', '.join(map(str, imu.columns)) or 'none'})")
    t = imu["t"].to_numpy(dtype=float)
    if not np.isfinite(t).all():
        raise ValueError(f"imu: {int((~np.isfinite(t)).sum())} sample(s) without a finite time t")
    if np.any(np.diff(t) < 0):
        k = int(np.argmax(np.diff(t) < 0))
        raise ValueError(f"imu: the times t must be in order (t = {t[k]!r} s, then {t[k + 1]!r} s)")
    a = imu[["ax", "ay", "az"]].to_numpy(dtype=float) / G0
    ok = np.isfinite(a).all(axis=1)
    t, a = t[ok], a[ok]
    n = len(t)
    if n == 0:
        return pd.DataFrame({c: [] for c in IMPACT_COLUMNS})
    csum = np.vstack([np.zeros((1, 3)), np.cumsum(a, axis=0)])
    i = np.arange(n)
    lo = np.minimum(np.searchsorted(t, t - rule.window_s, side="right"), i)   # t_j in (t_i - window_s, t_i], and i
    mean = (csum[i + 1] - csum[lo]) / (i + 1 - lo)[:, None]
    g = np.linalg.norm(mean, axis=1)
    spike = g - 1.0 > rule.impact_g

    def completed(run: np.ndarray, lasting: float) -> tuple[np.ndarray, np.ndarray]:
        """The samples that complete a run of ``run`` lasting ``lasting``, and each sample's run start."""
        begins = run & ~np.concatenate([[False], run[:-1]])
        since = np.maximum.accumulate(np.where(begins, i, 0))
        done = run & (t - t[since] >= lasting)
        return done & ~np.concatenate([[False], done[:-1]]), since

    fall, fell_since = completed(g < rule.freefall_g, rule.freefall_s)
    upside, up_since = completed(mean[:, 2] < -rule.inverted_g, rule.inverted_s)
    keep = _Refractory(rule.refractory_s)
    out = []
    for k in np.nonzero(spike | fall | upside)[0]:
        tk, gk = float(t[k]), float(g[k])
        if spike[k]:
            found = [_spike(rule, tk, gk)]
        else:
            found = [_fall(tk, gk, float(tk - t[fell_since[k]]))] if fall[k] else []
        if upside[k]:
            found.append(_inverted(tk, gk, float(tk - t[up_since[k]])))
        admitted = [imp for imp in found if keep.admit(imp)]
        out.extend(admitted[-1:])                                   # one per sample, as ImpactDetector
    return pd.DataFrame({"t": [m.t for m in out], "event": "impact", "detail": [m.detail for m in out],
                         "g": [m.g for m in out], "crash": np.array([m.crash for m in out], dtype=bool)},
                        columns=IMPACT_COLUMNS)


class ImpactDetector:
    """``impacts`` one IMU sample at a time: ``update(t, ax, ay, az)`` (s; m/s^2) returns the
    ``Impact`` that sample completes, or None. Holds the last ``window_s`` of samples; a time
    going back (a restarted clock) starts it afresh, a non-finite sample is left out."""

    def __init__(self, rule: ImpactRule = ImpactRule()):
        self.rule = rule
        self.reset()

    def reset(self) -> None:
        self._window: deque[tuple[float, float, float, float]] = deque()
        self._sx = self._sy = self._sz = 0.0
        self._fall = _Run(self.rule.freefall_s)
        self._upside = _Run(self.rule.inverted_s)
        self._last_t = -math.inf
        self._keep = _Refractory(self.rule.refractory_s)

    def update(self, t: float, ax: float, ay: float, az: float) -> Impact | None:
        if not (math.isfinite(ax) and math.isfinite(ay) and math.isfinite(az)):
            return None
        if t < self._last_t:
            self.reset()
        self._last_t = t
        ax, ay, az = ax / G0, ay / G0, az / G0
        w = self._window
        w.append((t, ax, ay, az))
        self._sx += ax
        self._sy += ay
        self._sz += az
        edge = t - self.rule.window_s
        while len(w) > 1 and w[0][0] <= edge:
            _, x, y, z = w.popleft()
            self._sx -= x
            self._sy -= y
            self._sz -= z
        n = len(w)
        g = math.sqrt(self._sx * self._sx + self._sy * self._sy + self._sz * self._sz) / n
        found = [_spike(self.rule, t, g)] if g - 1.0 > self.rule.impact_g else []
        fell = self._fall.update(g < self.rule.freefall_g, t)
        if fell is not None:
            found.append(_fall(t, g, fell))
        upside = self._upside.update(self._sz / n < -self.rule.inverted_g, t)
        if upside is not None:
            found.append(_inverted(t, g, upside))
        admitted = [imp for imp in found if self._keep.admit(imp)]
        return admitted[-1] if admitted else None
