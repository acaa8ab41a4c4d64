"""Batched products whose result for one flight does not depend on the batch.

BLAS picks kernels by size and memory alignment, so ``A @ B`` for a flight can round
differently alone and inside a batch. These products multiply elementwise and sum over
a non-innermost axis (accumulated in a fixed order), which keeps datasets bit-identical
whatever the batch size.
"""

from __future__ import annotations

import torch


def bmm(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(..., n, m) @ (..., m, k) -> (..., n, k)."""
    return (a.unsqueeze(-1) * b.unsqueeze(-3)).sum(-2)


def matvec(a: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """(..., n, m) @ (..., m) -> (..., n), accumulated column by column."""
    out = a[..., :, 0] * x[..., 0:1]
    for j in range(1, a.shape[-1]):
        out = out + a[..., :, j] * x[..., j:j + 1]
    return out
