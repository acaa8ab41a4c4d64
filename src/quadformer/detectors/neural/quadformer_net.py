"""QUADFormer network: a transformer over residue windows with a two-branch attention.

A window is first summarised into tokens (``detectors.context``: the last steps one by one,
earlier ones in patch means); the attention runs over the tokens, and "position" and
"distance" below are in GPS steps between the tokens' centres.

Each attention head computes
- a series association S = softmax(Q K^T / sqrt(d)), learned from the data, and
- a prior association P: a Gaussian kernel over the temporal distance |i - j| whose width
  sigma is predicted per head and position from the input, rows normalised to sum to 1
  (``prior_sigma``: a fixed width in steps instead, learned by nothing).
Normal steps spread their association over the window (far from the local prior); attacked
steps concentrate it on their neighbours (close to it). The per-step association
discrepancy, the symmetric KL between P and S averaged over heads and layers, is the
statistic that separates them. Heads: reconstruction of the (normalised) residues and a
per-step classification into normal and attack types.

This module is the model as trained and saved. Scoring runs its forward (``last_only``) written
out for inference from per-step projections (``quadformer_steps.StepNet``, the same numbers to
float32 rounding); ``forward`` on whole windows stays the reference it is tested against.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from quadformer.detectors.context import Context


def symmetric_kl(p: torch.Tensor, q: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """KL(p||q) + KL(q||p) over the last axis."""
    p = p.clamp_min(eps)
    q = q.clamp_min(eps)
    return ((p - q) * (p.log() - q.log())).sum(-1)


class TwoBranchAttention(nn.Module):
    def __init__(self, d_model: int, heads: int, positions: torch.Tensor, use_prior: bool = True,
                 prior_sigma: float | None = None):
        super().__init__()
        self.h, self.dk = heads, d_model // heads
        self.qkv = nn.Linear(d_model, 3 * d_model)
        # the prior's width: learned per head and position, or fixed (prior_sigma steps)
        self.sigma = nn.Linear(d_model, heads) if prior_sigma is None else None
        self.prior_sigma = prior_sigma
        self.out = nn.Linear(d_model, d_model)
        self.use_prior = use_prior
        pos = torch.as_tensor(positions, dtype=torch.float32)
        self.register_buffer("dist2", (pos[:, None] - pos[None, :]) ** 2, persistent=False)

    def forward(self, x: torch.Tensor, last_query: bool = False, last_row: bool = False):
        """last_row: return the associations of the last position only (B,H,1,W), all a causal
        score needs; last_query (with last_row: the final layer at scoring time): output only
        the last position, whose queries are then the only ones computed."""
        B, W, D = x.shape
        if last_query:
            q = nn.functional.linear(x[:, -1:], self.qkv.weight[:D], self.qkv.bias[:D])
            q = q.view(B, 1, self.h, self.dk).transpose(1, 2)
            k, v = nn.functional.linear(x, self.qkv.weight[D:], self.qkv.bias[D:]).view(
                B, W, 2, self.h, self.dk).permute(2, 0, 3, 1, 4)
        else:
            q, k, v = self.qkv(x).view(B, W, 3, self.h, self.dk).permute(2, 0, 3, 1, 4)
        if last_row:
            # the attention's output from the fused kernel (no (W, W) matrix kept) and the
            # series of the last position on its own: the same numbers to float rounding
            z = nn.functional.scaled_dot_product_attention(q, k, v)
            series = torch.softmax((q[:, :, -1:] * (1.0 / math.sqrt(self.dk))) @ k.transpose(-1, -2), dim=-1)
        else:
            series = torch.softmax(q @ k.transpose(-1, -2) / math.sqrt(self.dk), dim=-1)   # (B,H,W,W)
            z = series @ v
        z = z.transpose(1, 2).reshape(B, q.shape[2], D)
        if not self.use_prior:
            return self.out(z), series, None
        xs = x[:, -1:] if last_row else x
        if self.sigma is not None:
            # width in steps: at least 0.5, learned per head and position
            sigma = nn.functional.softplus(self.sigma(xs)).transpose(1, 2) + 0.5        # (B,H,W|1)
        else:
            sigma = xs.new_full((B, self.h, xs.shape[1]), float(self.prior_sigma))      # fixed width
        rows = self.dist2[W - 1:W, :W] if last_row else self.dist2[:W, :W]
        prior = torch.softmax(-rows / (2 * sigma[..., None] ** 2), dim=-1)  # normalised Gaussian rows
        return self.out(z), series, prior


class Layer(nn.Module):
    def __init__(self, d_model: int, heads: int, positions: torch.Tensor, use_prior: bool, dropout: float,
                 prior_sigma: float | None = None):
        super().__init__()
        self.attn = TwoBranchAttention(d_model, heads, positions, use_prior, prior_sigma)
        self.n1 = nn.LayerNorm(d_model)
        self.ff = nn.Sequential(nn.Linear(d_model, 2 * d_model), nn.GELU(), nn.Dropout(dropout),
                                nn.Linear(2 * d_model, d_model))
        self.n2 = nn.LayerNorm(d_model)
        self.drop = nn.Dropout(dropout)

    def forward(self, x, last_query: bool = False, last_row: bool = False):
        a, series, prior = self.attn(x, last_query, last_row)
        if last_query:
            x = x[:, -1:]
        x = self.n1(x + self.drop(a))
        x = self.n2(x + self.drop(self.ff(x)))
        return x, series, prior


class QUADFormerNet(nn.Module):
    def __init__(self, n_features: int, n_classes: int, context: Context, d_model: int = 64, heads: int = 4,
                 layers: int = 2, dropout: float = 0.1, use_prior: bool = True, prior_sigma: float | None = None):
        super().__init__()
        self.context = context
        self.embed = nn.Linear(n_features, d_model)
        positions = torch.from_numpy(context.positions())
        pos = positions[:, None]
        div = torch.exp(torch.arange(0, d_model, 2, dtype=torch.float32) * (-math.log(10000.0) / d_model))
        pe = torch.zeros(len(positions), d_model)
        pe[:, 0::2] = torch.sin(pos * div)
        pe[:, 1::2] = torch.cos(pos * div)
        self.register_buffer("pe", pe, persistent=False)
        self.layers = nn.ModuleList([Layer(d_model, heads, positions, use_prior, dropout, prior_sigma)
                                     for _ in range(layers)])
        self.recon = nn.Linear(d_model, n_features)
        self.classify = nn.Linear(d_model, n_classes)
        self.use_prior = use_prior

    def forward(self, x: torch.Tensor, last_only: bool = False, tokens: bool = False) -> dict[str, torch.Tensor]:
        """x: (B, W, features) windows. Returns their tokens (B,T,F) (``context.tokens``), the
        reconstruction of the tokens (B,T,F), class logits (B,T,C), and the per-layer series and
        prior associations (lists of (B,H,T,T); priors None without prior).

        last_only: outputs and associations of the last token only (T replaced by 1), all a
        causal score needs, at a fraction of the cost. The last token is the window's last step.
        tokens: x holds the windows' tokens already (B,T,F)."""
        tok = x if tokens else self.context.tokens(x)
        h = self.embed(tok) + self.pe
        series, priors = [], []
        for i, layer in enumerate(self.layers):
            final = i == len(self.layers) - 1
            h, s, p = layer(h, last_query=last_only and final, last_row=last_only)
            series.append(s)
            priors.append(p)
        return {"tokens": tok, "recon": self.recon(h), "logits": self.classify(h), "series": series,
                "priors": priors}


def last_parts(recon: torch.Tensor, logits: torch.Tensor, last_token: torch.Tensor, dis: torch.Tensor | None
               ) -> dict[str, torch.Tensor]:
    """Score ingredients of the last position of windows from its reconstruction (B, F), class
    logits (B, C) and association discrepancy (B,) (None without one), and the window's last
    token (B, F), as float32 tensors (type: int64): reconstruction error, discrepancy (zero
    without it), attack probability and the most likely attack class."""
    err = ((recon - last_token) ** 2).mean(-1)
    prob = torch.softmax(logits, dim=-1)
    return {"err": err, "dis": torch.zeros_like(err) if dis is None else dis, "p_attack": 1 - prob[:, 0],
            "type": prob[:, 1:].argmax(-1) + 1}


class _ReverseGrad(torch.autograd.Function):
    """Identity forward; negated gradient backward."""

    @staticmethod
    def forward(ctx, x):
        return x.view_as(x)

    @staticmethod
    def backward(ctx, g):
        return -g


def discrepancy(series: list[torch.Tensor], priors: list[torch.Tensor | None], mode: str = "both"
                ) -> torch.Tensor:
    """Association discrepancy per step (B, W), averaged over heads and layers.

    mode "both": plain gradients to both branches. mode "minimax": one evaluation whose
    gradient descends the discrepancy for the prior and ascends it for the series, i.e.
    the gradient of Dis(P, sg(S)) - Dis(sg(P), S) (the minimax pair), at half the cost.
    """
    out = 0.0
    for s, p in zip(series, priors):
        if p is None:
            continue
        if mode == "minimax":
            s = _ReverseGrad.apply(s)
        out = out + symmetric_kl(p, s).mean(1)
    return out / max(1, len(series))
