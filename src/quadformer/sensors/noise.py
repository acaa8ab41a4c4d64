"""Measurement noise shapes, all zero-mean with unit standard deviation before scaling.

- ``gaussian``: standard normal.
- ``exponential``: one-sided exponential shifted to zero mean (skewness 2, excess kurtosis 6).
- ``laplace``: Laplace with scale 1/sqrt(2) (skewness 0, excess kurtosis 3).
"""

from __future__ import annotations

import numpy as np

from quadformer.config import NOISE_SHAPES, ConfigError


def standard_noise(rng: np.random.Generator, shape: str, size: tuple[int, ...]) -> np.ndarray:
    """Zero-mean, unit-variance samples of the named shape."""
    if shape == "gaussian":
        return rng.standard_normal(size)
    if shape == "exponential":
        return rng.standard_exponential(size) - 1.0
    if shape == "laplace":
        return rng.laplace(0.0, 1.0 / np.sqrt(2.0), size)
    raise ConfigError(f"noise: unknown noise shape {shape!r}; choose from {', '.join(NOISE_SHAPES)}")


def batch_noise(gens: list[np.random.Generator], shape: str, size: tuple[int, ...]) -> np.ndarray:
    """One block of standard noise per flight, stacked: (flights, *size)."""
    return np.stack([standard_noise(g, shape, size) for g in gens])
