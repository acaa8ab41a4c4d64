"""GPS minus the GPS-free reference, rebuilt from a flight's rows for the shape typer
(``attack_types``): the reference residue ``res_ref_d`` is the smoothed difference minus an anchor;
``Unanchored`` adds the anchor back row by row and ``unsmooth`` undoes the smoothing, at the
reference's own step per row (``age_step``)."""

from __future__ import annotations

import numpy as np


class Unanchored:
    """GPS minus the reference, smoothed, without its anchor, row by row from a flight's first
    row: a_k = res_ref_d_k + a_j, j = k - age_k / step the row the anchor was taken at (the
    anchor is the smoothed difference of that row). ``step``: the reference's GPS step, which
    ``res_ref_age`` advances by per row; ``keep``: rows remembered (the anchor of a frozen
    disagreement is held however old)."""

    def __init__(self, step: float, keep: int = 1 << 30):
        self.step, self.keep = step, keep
        self.rows: dict[int, np.ndarray] = {}
        self.k = 0
        self.held: tuple[int, np.ndarray] = (-1, np.zeros(6))

    def push(self, r: np.ndarray, age: float) -> tuple[np.ndarray, int]:
        """(a of this row, the row its anchor was taken at) for a row's res_ref_d (6,) and res_ref_age."""
        k = self.k
        lag = max(1, int(round(age / self.step))) if np.isfinite(age) else 1
        j = k - lag
        base = self.rows.get(j, self.held[1] if self.held[0] == j else np.zeros(6) if j < 0 else None)
        a = np.asarray(r, dtype=float) + (base if base is not None else np.nan)
        if j in self.rows:
            self.held = (j, self.rows[j])
        # a row that cannot be rebuilt (non-finite) is NaN; the rows anchored on it later take
        # the last finite row instead (one step's change off, not NaN for the rest of the flight)
        self.rows[k] = a if np.isfinite(a).all() else self.rows.get(k - 1, np.zeros(6))
        self.rows.pop(k - self.keep, None)
        self.k += 1
        return a, j


def gps_step(t: np.ndarray) -> float:
    """The GPS step of a flight (s)."""
    steps = np.diff(t)
    steps = steps[np.isfinite(steps) & (steps > 0)]
    return float(np.median(steps)) if len(steps) else 0.1


def age_step(age: np.ndarray, t: np.ndarray) -> float:
    """The reference's GPS step: what ``res_ref_age`` advances by per row (while the anchor
    stands), else the rows' step. It is 1 / the filter's ``gps_rate_hz`` whatever the rate of
    the fixes: a log's 5 Hz receiver under the 10 Hz default advances it 0.1 s per fix."""
    inc = np.diff(age)
    inc = inc[np.isfinite(inc) & (inc > 1e-9) & (inc < 1.0)]
    return float(np.median(inc)) if len(inc) else gps_step(t)


def unsmooth(a: np.ndarray, step: float, tau: float) -> np.ndarray:
    """The raw rows d of rows a smoothed by a first-order lag of tau at ``step`` seconds per
    row: undo a_k = a_(k-1) + alpha (d_k - a_(k-1))."""
    alpha = 1.0 - np.exp(-step / tau)
    d = np.array(a, dtype=float, copy=True)
    d[1:] = a[:-1] + np.diff(a, axis=0) / alpha
    return d
