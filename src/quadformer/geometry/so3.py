"""SO(3) exponential and logarithm maps for unit quaternions (xyzw), batch invariant.

Vectorised transcendental kernels (atan2 in particular) round differently from their
scalar fallbacks, so a flight's result would depend on its position in the batch. For the
small angles of IMU increments, filter corrections and sensor noise (below 0.1 rad) we use
Taylor series made of +, * and sqrt only, exact to machine precision; larger angles fall
back to the trigonometric formulas.
"""

from __future__ import annotations

import roma
import torch

_SMALL = 0.1  # rad


def exp_quat(phi: torch.Tensor) -> torch.Tensor:
    """Rotation vector (..., 3) to unit quaternion (..., 4), xyzw."""
    th2 = (phi * phi).sum(-1, keepdim=True)
    x2 = th2 / 4.0                                   # (theta / 2)^2
    sinc = 1 - x2 / 6 * (1 - x2 / 20 * (1 - x2 / 42 * (1 - x2 / 72)))        # sin(x)/x
    cos = 1 - x2 / 2 * (1 - x2 / 12 * (1 - x2 / 30 * (1 - x2 / 56 * (1 - x2 / 90))))
    small = th2 < _SMALL**2
    if not bool(small.all()):
        th = torch.sqrt(th2)
        half = th / 2
        safe = torch.where(small, torch.ones_like(th), th)
        sinc = torch.where(small, sinc, 2 * torch.sin(half) / safe)
        cos = torch.where(small, cos, torch.cos(half))
    return torch.cat([phi / 2 * sinc, cos], dim=-1)


def log_quat(q: torch.Tensor) -> torch.Tensor:
    """Unit quaternion (..., 4), xyzw, to rotation vector (..., 3) with angle in [0, pi]."""
    q = torch.where(q[..., 3:4] < 0, -q, q)
    v, w = q[..., :3], q[..., 3:4]
    s2 = (v * v).sum(-1, keepdim=True)              # sin^2(theta / 2)
    # 2 asin(s) / s as a series in s^2 (valid for w >= 0)
    k = 2 * (1 + s2 * (1 / 6 + s2 * (3 / 40 + s2 * (5 / 112 + s2 * (35 / 1152 + s2 * 63 / 2816)))))
    small = s2 < (_SMALL / 2) ** 2
    if not bool(small.all()):
        s = torch.sqrt(s2)
        safe = torch.where(small, torch.ones_like(s), s)
        k = torch.where(small, k, 2 * torch.atan2(s, w) / safe)
    return v * k


def exp_rotmat(phi: torch.Tensor) -> torch.Tensor:
    """Rotation vector (..., 3) to rotation matrix (..., 3, 3)."""
    return roma.unitquat_to_rotmat(exp_quat(phi))
