"""The vehicle the shape typer's hand-made tests fly: a circle of 5 m radius at 0.3 rad/s, 10 m up,
and its GPS fixes (truth + white noise of 0.3 m and 0.05 m/s)."""

from __future__ import annotations

import numpy as np


def circle(seed: int, duration: float, rate: float):
    """(the flight's generator after the fixes' draws, t, true position, true velocity, fixes (n, 6))."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration, 1.0 / rate)
    w = 0.3
    p = np.stack([5 * np.cos(w * t), 5 * np.sin(w * t), 10 + 0 * t], 1)
    v = np.stack([-5 * w * np.sin(w * t), 5 * w * np.cos(w * t), 0 * t], 1)
    fix = np.concatenate([p + rng.normal(0, 0.3, p.shape), v + rng.normal(0, 0.05, v.shape)], 1)
    return rng, t, p, v, fix
