"""What a spoof's shape is fitted against: the noise in GPS minus the GPS-free reference.

GPS minus the reference, its anchor taken off (``reference_rows.Unanchored``), is the spoof plus
the GPS's white noise plus the reference's own error. With a camera the reference's velocity is
held by the VIO velocity and its error barely shows: the rows are white noise about a constant
(and, in position, a slow slope). Without one (IMU, magnetometer, barometer) the reference
integrates the IMU alone: its velocity error wanders (a random walk between its resets) by
about a metre per second within seconds and its position error is that walk summed, more than
many spoofs. Fitted as if every row's error were independent, the wander is taken for a shape:
a bias the reference then drifts away from looks like a ramp or half a sinusoid, and the same
flight replayed through a filter of other tuning (a flight log through ``detect``) wanders
otherwise and is typed otherwise.

Where the reference states (``res_ref_d / res_ref_w`` in velocity) more uncertainty than the
white noise of the velocity difference (``DRIFT_RATIO``: 0.3 to 0.7 of it with a camera, 1.1 to
9 without one, over the axes of 80 flights of each), each axis is modelled as white noise
(variance r) plus the reference's drift: in velocity a random walk of variance q per row, in
position that walk summed (its slope walks by q dt^2 per row, dt the row's step). r and q come
from the rows: the robust variances of the differences of the velocity difference over 1 to 32
rows grow as 2 r + L q with the lag L (fitted by non-negative least squares; each variance the
median of those of consecutive pieces, from the rows before the last 10 s: a spoof being typed
is in the last seconds, and a frozen fix has no noise of its own), r of the position from its
second differences over one row (6 r). Each channel is whitened by
the steady-state innovations of its model (the difference of order d over the model's
moving-average polynomial: ``Whitener``), and the unknown start of the walk (a constant in
velocity; a constant and a slope in position) is projected out, so a shape is fitted by least
squares on white residuals. Without a drift the rows are only scaled: the fit with a free
constant (and slope) and independent rows.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import nnls


def lfilter(b, a, x, axis=-1):
    """scipy.signal.lfilter, imported on first use (scipy.signal loads scipy.stats, which a run that
    types no alert need not pay for)."""
    from scipy.signal import lfilter as _lfilter

    return _lfilter(b, a, x, axis=axis)


#: lags (rows) of the differences whose variances give the drift
LAGS = (1, 2, 4, 8, 16, 32)
#: a drift is modelled on an axis where the reference states more than this many times the white
#: noise of the velocity difference
DRIFT_RATIO = 1.0
#: the differences' variances are the median of those of up to PIECES consecutive pieces, each
#: of at least PIECE_ROWS differences
PIECES = 5
PIECE_ROWS = 40
#: the noise is estimated from the rows before the last RECENT_S seconds where they are this many
#: (a spoof being typed is in the last seconds; a frozen fix has no noise of its own), else from all
RECENT_S = 10.0
NOISE_ROWS = 80
#: the least drift variance, as a share of the white variance (keeps the whitening stable)
FLOOR = 1e-9


def robust_var(x: np.ndarray) -> float:
    """Variance of x from its median absolute deviation (NaN with fewer than 8 finite values)."""
    x = x[np.isfinite(x)]
    if len(x) < 8:
        return float("nan")
    return float((1.4826 * np.median(np.abs(x - np.median(x)))) ** 2)


def lag_variances(y: np.ndarray, order: int) -> dict[int, float]:
    """Robust variances of y's differences of ``order`` (1 or 2) at each of ``LAGS`` the rows allow."""
    out = {}
    for lag in LAGS:
        if len(y) > order * lag + 8:
            d = y[lag:] - y[:-lag] if order == 1 else y[2 * lag:] - 2 * y[lag:-lag] + y[:-2 * lag]
            pieces = max(1, min(PIECES, len(d) // PIECE_ROWS))
            v = float(np.nanmedian([robust_var(p) for p in np.array_split(d, pieces)]))
            if np.isfinite(v):
                out[lag] = v
    return out


def walk(var: dict[int, float]) -> tuple[float, float]:
    """(r, q): the white variance and the random walk's per row of a velocity difference, from
    its lag variances (2 r + L q)."""
    lags = np.array(sorted(var), dtype=float)
    b = np.array([var[int(L)] for L in lags])
    if len(lags) < 2:
        return b[0] / 2.0, 0.0
    x = nnls(np.column_stack([np.full(len(lags), 2.0), lags]) / b[:, None], np.ones(len(b)))[0]
    return max(float(x[0]), 1e-3 * b.min() / 2.0, 1e-12), float(x[1])


def _ma_factor(acov: np.ndarray) -> tuple[np.ndarray, float]:
    """The invertible moving-average polynomial theta (theta[0] = 1) and innovation variance of
    a process of autocovariances acov[0..d]."""
    d = len(acov) - 1
    roots = np.roots(np.r_[acov[::-1], acov[1:]])           # pairs z, 1/z
    outside = roots[np.argsort(-np.abs(roots))][:d]
    theta = np.real(np.poly(1.0 / outside))                 # prod (1 - B / z_i)
    return theta, float(acov[0] / np.sum(theta ** 2))


class Whitener:
    """Whitens one channel of one axis over a window of n rows: ``white(x)`` is the model's
    standardised innovations of x with the start of the drift (``order`` terms: a constant, and
    a slope for 2) projected out. ``r``: the white variance; ``q``: the drift's variance per
    row (order 1: a random walk; order 2: the walk of the slope), 0 for none."""

    def __init__(self, r: float, q: float, order: int, n: int):
        if q > 0:
            acov = np.array([2 * r + q, -r]) if order == 1 else np.array([6 * r + q, -4 * r, r])
            theta, var = _ma_factor(acov)
            self.b = np.poly(np.ones(order)) / np.sqrt(var)     # the difference of order d
            self.a = theta
        else:
            self.b, self.a = np.array([1.0 / np.sqrt(r)]), np.array([1.0])
        N = np.stack([self.filt(np.arange(n, dtype=float) ** j) for j in range(order)], 1)
        self.U = np.linalg.qr(N)[0]                              # the start of the drift, orthonormal

    def filt(self, x: np.ndarray) -> np.ndarray:
        """The innovations of x along its last axis (from a zero start)."""
        return lfilter(self.b, self.a, x, axis=-1)

    def project(self, x: np.ndarray) -> np.ndarray:
        """x (.., n) without its part along the start of the drift."""
        return x - (x @ self.U) @ self.U.T

    def white(self, x: np.ndarray) -> np.ndarray:
        return self.project(self.filt(x))


def whiteners(up: np.ndarray, uv: np.ndarray, stated: np.ndarray, n: int,
              step: float) -> tuple[list[Whitener], list[Whitener]] | None:
    """The position and velocity whiteners of each axis for a window of n rows of ``step``
    seconds, their noise estimated from ``up`` and ``uv`` (rows, 3), the unanchored differences
    up to the row typed (but the last ``RECENT_S`` seconds: ``NOISE_ROWS``), with the reference's
    drift where it states (``stated``: (rows, 3), the std of its velocity difference) more than
    ``DRIFT_RATIO`` times their white velocity noise. None where the rows are too few."""
    wp, wv = [], []
    recent = int(round(RECENT_S / step))
    older = slice(0, len(up) - recent) if len(up) - recent >= NOISE_ROWS else slice(None)
    for ax in range(3):
        vp, vv = lag_variances(up[older, ax], 2), lag_variances(uv[older, ax], 1)
        if 1 not in vp or 1 not in vv:
            return None
        said = stated[:, ax][np.isfinite(stated[:, ax])]
        drift = len(said) > 0 and float(np.median(said)) > DRIFT_RATIO * np.sqrt(vv[1] / 2.0)
        r, q = walk(vv) if drift else (vv[1] / 2.0, 0.0)
        r_p = max(vp[1] / 6.0, 1e-12)
        wp.append(Whitener(r_p, max(q * step ** 2, FLOOR * r_p) if drift else 0.0, 2, n))
        wv.append(Whitener(max(r, 1e-12), max(q, FLOOR * r) if drift else 0.0, 1, n))
    return wp, wv
