"""1D convolutional network over a residue window's tokens (``detectors.context``)."""

from __future__ import annotations

import torch
from torch import nn

from quadformer.detectors.context import Context


class CNN1d(nn.Module):
    def __init__(self, n_features: int, context: Context, channels: int = 32, kernel: int = 5):
        super().__init__()
        self.context = context
        pad = kernel // 2
        self.body = nn.Sequential(
            nn.Conv1d(n_features, channels, kernel, padding=pad), nn.ReLU(),
            nn.Conv1d(channels, channels, kernel, padding=2 * pad, dilation=2), nn.ReLU(),
            nn.Conv1d(channels, channels, kernel, padding=4 * pad, dilation=4), nn.ReLU(),
        )
        self.head = nn.Linear(2 * channels + channels, 1)

    def forward(self, x: torch.Tensor, tokens: bool = False) -> torch.Tensor:
        """x: (batch, W, features) windows, or their tokens (batch, T, features) with
        ``tokens=True`` -> logit of the window's last step (batch,)."""
        h = self.body((x if tokens else self.context.tokens(x)).transpose(1, 2))    # (B, C, tokens)
        pooled = torch.cat([h.mean(-1), h.amax(-1), h[..., -1]], dim=-1)
        return self.head(pooled).squeeze(-1)
