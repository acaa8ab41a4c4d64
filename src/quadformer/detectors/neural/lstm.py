"""LSTM over a residue window (short-term dependencies)."""

from __future__ import annotations

import torch
from torch import nn


class LSTMNet(nn.Module):
    def __init__(self, n_features: int, hidden: int = 64, layers: int = 1):
        super().__init__()
        self.lstm = nn.LSTM(n_features, hidden, num_layers=layers, batch_first=True)
        self.head = nn.Linear(hidden, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (batch, W, features) -> logit of the window's last step (batch,)."""
        out, _ = self.lstm(x)
        return self.head(out[:, -1]).squeeze(-1)
