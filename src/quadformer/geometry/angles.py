"""Plane angles, batch invariant.

``torch.atan2`` runs a vectorised kernel on most of a tensor and a scalar one on the rest,
which round differently: a flight's heading innovation would depend on its position in the
batch. ``atan2`` here uses +, -, *, / and sqrt only (correctly rounded in every kernel):
the angle is halved six times with the half-angle formulas, then an arctangent series
(|t| < 0.05) gives it to about 1e-15 rad.
"""

from __future__ import annotations

import math

import torch

_HALVINGS = 6


def atan2(y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Angle of the vector (x, y) in [-pi, pi], elementwise; 0 for the zero vector."""
    r = torch.sqrt(x * x + y * y)
    zero = r == 0
    r = torch.where(zero, torch.ones_like(r), r)
    c = torch.where(zero, torch.ones_like(r), x / r)
    s = torch.where(zero, torch.zeros_like(r), y / r)
    # first halving, stable on both sides: from cos >= 0, or from |sin| >= 1/sqrt(2)
    ch = torch.sqrt((1 + c) / 2)
    sh = torch.where(s >= 0, 1.0, -1.0) * torch.sqrt((1 - c) / 2)
    front = c >= 0
    c, s = torch.where(front, ch, s / (2 * sh)), torch.where(front, s / (2 * ch), sh)
    for _ in range(_HALVINGS - 1):       # the half angle is within (-pi/2, pi/2]: cos >= 0
        ch = torch.sqrt((1 + c) / 2)
        c, s = ch, s / (2 * ch)
    t = s / c
    t2 = t * t
    series = t * (1 - t2 * (1 / 3 - t2 * (1 / 5 - t2 * (1 / 7 - t2 * (1 / 9 - t2 * (1 / 11))))))
    return series * float(2**_HALVINGS)


def wrap_angle(a: torch.Tensor) -> torch.Tensor:
    """Angles in [-pi, pi] mapped to [-pi, pi)."""
    return torch.where(a >= math.pi, a - 2 * math.pi, a)
