"""LSTM over a residue window's tokens (``detectors.context``)."""

from __future__ import annotations

import torch
from torch import nn

from quadformer.detectors.context import Context


class LSTMNet(nn.Module):
    def __init__(self, n_features: int, context: Context, hidden: int = 64, layers: int = 1):
        super().__init__()
        self.context = context
        self.lstm = nn.LSTM(n_features, hidden, num_layers=layers, batch_first=True)
        self.head = nn.Linear(hidden, 1)

    def forward(self, x: torch.Tensor, tokens: bool = False) -> torch.Tensor:
        """x: (batch, W, features) windows, or their tokens (batch, T, features) with
        ``tokens=True`` -> logit of the window's last step (batch,)."""
        out, _ = self.lstm(x if tokens else self.context.tokens(x))
        return self.head(out[:, -1]).squeeze(-1)
