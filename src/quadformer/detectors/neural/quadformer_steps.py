"""QUADFormer scored from per-step projections: the network's numbers without recomputing
each window's linear start.

The network begins linearly. A token is the mean of its steps (a patch mean, or one step),
embedded by a linear map ``E x + b`` plus the positional encoding ``pe`` of its position, and
the first layer's queries, keys and values are a linear map ``W (.) + c`` of that embedding.
So each normalised step x is projected once, ``u = x P`` with ``P = [E; W E]^T`` (features ->
d_model + 3 d_model), and a token's embedding and first-layer q, k, v are the mean of its
steps' projections plus a constant of its position, ``C = [b + pe, W (b + pe) + c]``. This is
the network's own arithmetic reassociated: equal up to float32 rounding (the sums run in
another order), and the model itself is unchanged. Scores agree with the network on whole
windows to 1e-4 relative (tested; on the benchmark's fitted model 5e-5 at most, most of it
where the attack probability is near zero and its float32 value, 1 - p(none), is coarse).

Everything after that depends on the whole window and is computed per window: the first layer
attends over all tokens (bidirectionally), and every token's content changes as the window
slides (the patches shift by one step, a fine step moves to another position and encoding), so
no later quantity carries over from one window to the next. The first layer runs over all T
tokens and the final layer for the last query only, as ``QUADFormerNet.forward(...,
last_only=True)``; what a window saves is the embedding and, offline, the first layer's q, k, v
projections (together about a third of the multiply-adds of a scored step), and online the
gathering of the window.

- Offline (``projected_batches``): the steps a chunk of windows covers are projected once and
  their sliding patch means taken from float64 cumulative sums; a batch of windows reads its
  tokens from them through strided views (consecutive windows share their steps), and the
  network runs on the batch (``StepNet.score``).
- Online (``StepNet.forward``): the state is the steps' embeddings ``x E^T`` only (d_model
  wide, a quarter of the projection: each step reads a quarter of the state, which is most of
  the cost of keeping it, and the first layer's q, k, v of the window's 50 tokens are one
  product). The token means of the embeddings before the new step come from the stream's state
  (``detectors.context.StepTokens``: the last embeddings and their prefix sums), the new step
  is embedded and appended, and its embedding returned to be kept. The exported streaming
  graph (``detectors.export``) is this with the normalisation in front: the state is passed in
  and out, the graph holds none.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from quadformer.detectors.context import Context
from quadformer.detectors.neural.quadformer_net import QUADFormerNet, last_parts, symmetric_kl
from quadformer.detectors.windows import Windows

#: windows per network call offline (one thread): large enough for the matrix products to run
#: near the core's speed, small enough for a batch's intermediate tensors to stay in cache
BATCH = 128
#: steps projected at a time offline (the chunk's windows, plus the window's length before them)
CHUNK_ROWS = 4096


class StepNet(nn.Module):
    """A fitted ``QUADFormerNet`` (its parameters shared, not copied) scored from step
    projections: see the module text. ``proj`` (features, 4 d_model) and ``const`` (tokens,
    4 d_model) are derived from the network's weights in float64 and kept in float32.

    ``score`` and ``forward`` are the network's forward with ``last_only=True`` written out in
    functional form for inference (eval mode: no dropout) with fewer, larger operations: one step
    online is a hundred small calls whose fixed cost is most of its time. Prepared once from the
    weights (plain tensors, derived, never saved): the queries' scale 1/sqrt(d_head) folded
    into the query weights (a power of two for the default 16-wide heads, so the same numbers);
    every layer's prior width weights side by side, so that the priors of all layers are one
    batched product and one softmax; the last row of the distances. The final layer's
    last-position series association, which the score needs anyway, also weighs its values.
    The other layers take their output, on batches of windows (``score``), from PyTorch's fused
    attention kernel, the faster there, and on one step of a few windows (``forward``, and the
    exported streaming graph) from the full series association, whose last row is then the one
    the score reads (fewer operations). The discrepancy's mean over layers and heads is one mean
    over both. Equal to the network's forward to float32 rounding (tested against
    ``QUADFormer.score_windows``)."""

    def __init__(self, net: QUADFormerNet, disc: bool):
        super().__init__()
        self.net = net
        self.disc = disc
        d = self.d = net.embed.out_features
        layers = net.layers
        first = layers[0].attn
        self.heads, self.dk = first.h, first.dk
        scale = torch.ones(4 * d, dtype=torch.float64, device=net.embed.weight.device)
        scale[d:2 * d] = 1.0 / math.sqrt(first.dk)           # the query columns
        with torch.no_grad():
            e, b = net.embed.weight.double(), net.embed.bias.double()
            w, c = first.qkv.weight.double(), first.qkv.bias.double()
            base = b + net.pe.double()                                   # (T, D)
            proj = torch.cat([e.T, e.T @ w.T], dim=1) * scale            # (F, 4D)
            const = torch.cat([base, base @ w.T + c], dim=1) * scale     # (T, 4D)
            self.proj, self.const = proj.float(), const.float()
            self.embed_proj, self.embed_const = self.proj[:, :d].contiguous(), self.const[:, :d].contiguous()
            # per layer: scaled q, k, v weights, then those of the output, the norms and the MLP
            self.layer_weights = [
                (la.attn.qkv.weight * scale[d:, None].float(), la.attn.qkv.bias * scale[d:].float(),
                 la.attn.out.weight, la.attn.out.bias, la.n1.weight, la.n1.bias, la.n1.eps,
                 la.ff[0].weight, la.ff[0].bias, la.ff[3].weight, la.ff[3].bias, la.n2.weight, la.n2.bias, la.n2.eps)
                for la in layers]
            self.heads_weights = (net.recon.weight, net.recon.bias, net.classify.weight, net.classify.bias)
            t = len(net.pe)
            # -dist2 / 2 of the last position (the prior is softmax(-dist2 / (2 sigma^2)):
            # halving is exact in floating point, so the quotient is the same number)
            self.half_dist2 = -first.dist2[t - 1, :t] / 2
            self.learned_prior = first.use_prior and first.sigma is not None
            if self.learned_prior:
                self.sigma_weight = torch.stack([la.attn.sigma.weight.T for la in layers])       # (L, D, H)
                self.sigma_bias = torch.stack([la.attn.sigma.bias[None] for la in layers])       # (L, 1, H)
            elif first.use_prior:                                        # one fixed width
                sigma = torch.full((1,), float(first.prior_sigma), dtype=torch.float32, device=scale.device)
                self.fixed_prior = torch.softmax(self.half_dist2 / sigma ** 2, dim=-1)

    @property
    def width(self) -> int:
        """Length of a step's embedding, the state kept online per step (d_model)."""
        return self.d

    def project(self, x: torch.Tensor) -> torch.Tensor:
        """Projections of normalised steps (..., features) -> (..., 4 d_model): embedding and
        first-layer q, k, v, without the constants of the token positions."""
        return x @ self.proj

    def forward(self, x: torch.Tensor, context: torch.Tensor) -> dict[str, torch.Tensor]:
        """One step of each window: its normalised last step x (B, features) and the token means
        of the embeddings of the window's earlier steps, ``context`` (B, T-1, d_model) -> the
        score ingredients (``score``) and ``embedding``, the step's embedding (B, d_model) to
        keep. Online the state is the steps' embeddings (a quarter of their projections: a step
        reads less of it) and the first layer's q, k, v are computed from the tokens."""
        e = x @ self.embed_proj
        parts = self._score(torch.cat([context, e[:, None]], dim=1) + self.embed_const, None, x, fused=False)
        parts["embedding"] = e
        return parts

    def score(self, tokens: torch.Tensor, last: torch.Tensor) -> dict[str, torch.Tensor]:
        """Score ingredients (``quadformer_net.last_parts``) of windows given by their tokens, the
        token means of step projections plus ``const`` (B, T, 4 d_model), and their normalised
        last steps (B, features)."""
        return self._score(tokens[..., :self.d], tokens[..., self.d:], last, fused=True)

    def _score(self, h: torch.Tensor, qkv: torch.Tensor | None, last: torch.Tensor, fused: bool
               ) -> dict[str, torch.Tensor]:
        """``score`` from the tokens' embeddings h (B, T, d_model) and first-layer q, k, v (B, T,
        3 d_model; None: computed here from h); ``fused``: the fused attention kernel."""
        B, T = h.shape[:2]
        d, heads, dk = self.d, self.heads, self.dk
        series, inputs = [], []
        n = len(self.layer_weights)
        for i, (w, b, wo, bo, g1, b1, e1, wf1, bf1, wf2, bf2, g2, b2, e2) in enumerate(self.layer_weights):
            if i == n - 1:                            # the final layer: the last query only
                x = h[:, -1]
                if qkv is None:
                    q, kv = F.linear(x, w[:d], b[:d]), F.linear(h, w[d:], b[d:])
                else:
                    q, kv = qkv[:, -1, :d], qkv[..., d:]
                k, v = kv.view(B, T, 2, heads, dk).permute(2, 0, 3, 1, 4)
                s = torch.softmax(q.view(B, heads, 1, dk) @ k.transpose(-1, -2), dim=-1)
                z = (s @ v).reshape(B, d)
                inputs.append(x)
            else:
                x = h
                if qkv is None:
                    qkv = F.linear(h, w, b)
                q, k, v = qkv.view(B, T, 3, heads, dk).permute(2, 0, 3, 1, 4)
                if fused:
                    z = F.scaled_dot_product_attention(q, k, v, scale=1.0)
                    s = torch.softmax(q[:, :, -1:] @ k.transpose(-1, -2), dim=-1)
                else:
                    weights = torch.softmax(q @ k.transpose(-1, -2), dim=-1)
                    z, s = weights @ v, weights[:, :, -1:]
                z = z.transpose(1, 2).reshape(B, T, d)
                inputs.append(x[:, -1])
            series.append(s)
            x = F.layer_norm(x + F.linear(z, wo, bo), (d,), g1, b1, e1)
            h = F.layer_norm(x + F.linear(F.gelu(F.linear(x, wf1, bf1)), wf2, bf2), (d,), g2, b2, e2)
            qkv = None
        dis = None
        if self.disc:     # all layers at once: (L, B, H, T) associations, the mean over layers and heads
            s = torch.cat(series, dim=2).permute(2, 0, 1, 3)
            if self.learned_prior:
                sigma = F.softplus(torch.baddbmm(self.sigma_bias, torch.stack(inputs), self.sigma_weight)) + 0.5
                p = torch.softmax(self.half_dist2 / sigma[..., None] ** 2, dim=-1)
            else:
                p = self.fixed_prior
            dis = symmetric_kl(p, s).mean((0, 2))
        wr, br, wc, bc = self.heads_weights
        return last_parts(F.linear(h, wr, br), F.linear(h, wc, bc), last, dis)


def patch_means(u: torch.Tensor, patch: int) -> torch.Tensor:
    """Means of every ``patch`` consecutive rows of u (S, D) -> (S - patch + 1, D): row i is the
    mean of rows i .. i + patch - 1, from float64 cumulative sums, rounded to float32."""
    c = torch.cumsum(u.double(), dim=0)
    c = torch.cat([c.new_zeros(1, u.shape[1]), c])
    return ((c[patch:] - c[:-patch]) / patch).float()


def embedded_tokens(step_net: StepNet, u: torch.Tensor, means: torch.Tensor, starts: np.ndarray,
                    context: Context) -> torch.Tensor:
    """The embedded tokens (``StepNet.score``) of the windows beginning at rows ``starts`` of
    the step projections u (S, 4 d_model), ``means`` their ``patch_means``: (len(starts), T,
    4 d_model). Windows of consecutive starts read u and means through strided views, the
    constants added in the same pass; nothing is gathered."""
    n, width = len(starts), u.shape[1]
    out = torch.empty(n, context.n_tokens, width, dtype=u.dtype, device=u.device)
    npatch, split = context.n_patches, context.n_patches * context.patch
    const = step_net.const
    cuts = [0, *(np.flatnonzero(np.diff(starts) != 1) + 1).tolist(), n]
    for a, b in zip(cuts[:-1], cuts[1:]):
        s = int(starts[a])
        if npatch:
            coarse = means.as_strided((b - a, npatch, width), (width, context.patch * width, 1),
                                       means.storage_offset() + s * width)
            torch.add(coarse, const[:npatch], out=out[a:b, :npatch])
        fine = u.as_strided((b - a, context.fine, width), (width, width, 1), u.storage_offset() + (s + split) * width)
        torch.add(fine, const[npatch:], out=out[a:b, npatch:])
    return out


def projected_batches(step_net: StepNet, win: Windows, idx: np.ndarray, context: Context, batch: int = BATCH
                      ) -> Iterator[tuple[np.ndarray, torch.Tensor, torch.Tensor]]:
    """(positions in idx, embedded tokens (B, T, 4 d_model), last normalised steps (B,
    features)) of batches of the windows idx (in any order), the steps of each chunk of windows
    (``Windows.spans``) projected once."""
    dev = step_net.proj.device
    for pos, rows, starts in win.spans(idx, CHUNK_ROWS):
        x = torch.from_numpy(rows).to(dev)
        u = step_net.project(x)
        means = patch_means(u, context.patch) if context.n_patches else u
        for i in range(0, len(pos), batch):
            s = starts[i:i + batch]
            yield (pos[i:i + batch], embedded_tokens(step_net, u, means, s, context),
                   x[torch.from_numpy(s + win.width - 1).to(dev)])
