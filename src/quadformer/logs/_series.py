"""Small time-series helpers shared by the readers (matching and resampling by time)."""

from __future__ import annotations

import numpy as np

from quadformer.geometry.frames import quat_normalize


def relative_ticks(stamps: np.ndarray, start: int) -> np.ndarray:
    """Integer clock stamps minus ``start``, in signed 64-bit arithmetic.

    Unsigned stamps earlier than ``start`` would wrap around to ~1.8e19 ticks when
    subtracted as unsigned integers; here they become negative. Values beyond the int64
    range (only in damaged files) wrap silently."""
    s = np.asarray(stamps)
    if s.dtype.kind == "u":
        s = s.astype(np.uint64).view(np.int64)
    start = int(start) % (1 << 64)
    start = start - (1 << 64) if start >= (1 << 63) else start   # the same int64 view
    with np.errstate(over="ignore"):
        return s.astype(np.int64) - np.int64(start)


def relative_seconds(stamps: np.ndarray, start: int, scale: float) -> np.ndarray:
    """Clock stamps -> float seconds after ``start`` (``relative_ticks`` times scale, the
    seconds per tick)."""
    s = np.asarray(stamps)
    if s.dtype.kind not in "iu":   # a damaged format definition can change the field type
        with np.errstate(all="ignore"):
            return (s.astype(np.float64) - float(start)) * scale
    return relative_ticks(s, start).astype(np.float64) * scale


def median_period(t: np.ndarray) -> float:
    d = np.diff(np.asarray(t, dtype=float))
    d = d[np.isfinite(d) & (d > 0)]
    return float(np.median(d)) if len(d) else np.inf


def nearest_index(t_dst: np.ndarray, t_src: np.ndarray, tolerance: float) -> np.ndarray:
    """For each t_dst, the index of the nearest t_src (sorted) within tolerance, else -1."""
    t_dst = np.asarray(t_dst, dtype=float)
    t_src = np.asarray(t_src, dtype=float)
    if len(t_src) == 0:
        return np.full(len(t_dst), -1)
    hi = np.clip(np.searchsorted(t_src, t_dst), 0, len(t_src) - 1)
    lo = np.clip(hi - 1, 0, len(t_src) - 1)
    with np.errstate(invalid="ignore"):
        pick = np.where(np.abs(t_src[lo] - t_dst) <= np.abs(t_src[hi] - t_dst), lo, hi)
        ok = np.abs(t_src[pick] - t_dst) <= tolerance
    return np.where(ok, pick, -1)


def take(values: np.ndarray, index: np.ndarray) -> np.ndarray:
    """values[index] with NaN where index is -1."""
    values = np.asarray(values, dtype=float)
    out = values[np.clip(index, 0, max(len(values) - 1, 0))] if len(values) else \
        np.full((len(index),) + values.shape[1:], np.nan)
    mask = (index < 0).reshape((-1,) + (1,) * (out.ndim - 1))
    return np.where(mask, np.nan, out)


def step_lookup(t_dst: np.ndarray, t_src: np.ndarray, v_src: np.ndarray) -> np.ndarray:
    """Value of a piecewise-constant signal at t_dst: the latest v_src at or before t_dst
    (the first value before the first sample)."""
    i = np.searchsorted(np.asarray(t_src, float), np.asarray(t_dst, float), side="right") - 1
    return np.asarray(v_src)[np.clip(i, 0, len(v_src) - 1)]


def interp_linear(t_dst: np.ndarray, t_src: np.ndarray, v_src: np.ndarray) -> np.ndarray:
    """Linear interpolation of columns v_src (n, k) at t_dst; NaN outside [t_src[0], t_src[-1]]."""
    t_src = np.asarray(t_src, float)
    v_src = np.asarray(v_src, float).reshape(len(t_src), -1)
    t_dst = np.asarray(t_dst, float)
    out = np.full((len(t_dst), v_src.shape[1]), np.nan)
    if len(t_src) < 2:
        return out
    inside = (t_dst >= t_src[0]) & (t_dst <= t_src[-1])
    for k in range(v_src.shape[1]):
        out[inside, k] = np.interp(t_dst[inside], t_src, v_src[:, k])
    return out


def quat_interp(t_dst: np.ndarray, t_src: np.ndarray, q_src: np.ndarray) -> np.ndarray:
    """Normalised linear interpolation of (x, y, z, w) quaternions, sign-aligned to each
    predecessor first; NaN outside the source time range."""
    q = np.asarray(q_src, float).copy()
    if len(q) > 1:
        flips = np.where(np.sum(q[1:] * q[:-1], axis=1) < 0, -1.0, 1.0)
        q[1:] *= np.cumprod(flips)[:, None]
    return quat_normalize(interp_linear(t_dst, t_src, q))


def row_max(values: np.ndarray) -> np.ndarray:
    """Largest finite value of each row (n, k); NaN for a row without one."""
    v = np.asarray(values, dtype=float).reshape(len(values), -1)
    finite = np.isfinite(v)
    out = np.where(finite, v, -np.inf).max(axis=1, initial=-np.inf)
    return np.where(finite.any(axis=1), out, np.nan)


def first_fix(gps: dict) -> tuple[float, float, float]:
    """(lat, lon, alt) of the earliest fix of raw GPS columns ``t``, ``lat``, ``lon``, ``alt``."""
    i = int(np.argmin(np.where(np.isfinite(gps["t"]), gps["t"], np.inf)))
    return float(gps["lat"][i]), float(gps["lon"][i]), float(gps["alt"][i])
