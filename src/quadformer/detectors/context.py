"""Long context at a fixed cost: a window of many GPS steps as a short sequence of tokens.

A spoof that the filter absorbs leaves its clearest evidence at its onset, which a slow
drift or a long attack pushes far back in time. Every window detector therefore looks at a
long causal window (``window`` steps, 320 by default: 32 s at 10 Hz) summarised the same way:

- the last ``fine`` steps (32 by default) one token each, at full resolution: the onset of a
  fresh attack, intermittent on/off patterns;
- the ``window - fine`` steps before them as means of ``patch`` consecutive steps (16 by
  default: 1.6 s each), oldest first: the slow levels and trends of the last half minute.

With the defaults a 320-step window becomes 18 + 32 = 50 tokens: ten times the span of the
former 32-step window at under twice its tokens. The summary is the first operation of each
network (so an exported graph and the online ring buffer apply it too) and the input of the
window-based SVM and PCA. ``window == fine`` is a plain window of ``fine`` steps (a model saved
with a short window loads and scores as before).

Token positions (``positions``) are the centres of the steps they cover, in steps from the
window's first step; QUADFormer's positional encoding and the distance in its prior
association use them, so a coarse token sits where its steps were.

A token is a mean of steps, so a linear map of the tokens is the same mean of the mapped steps.
``StepTokens`` keeps, online, what the tokens of a window need from any per-step vectors (a
network's step projections): the last ``fine`` vectors and the float64 prefix sums of the last
``window``, from which each patch mean is one difference; a step costs the same whatever the
window's length.
"""

from __future__ import annotations

import numpy as np

#: the defaults of every window detector: 320 steps, the last 32 at full resolution, the
#: rest in means of 16
WINDOW, FINE, PATCH = 320, 32, 16


class Context:
    """Tokens of windows ``(n, window, features)`` -> ``(n, n_tokens, features)``."""

    def __init__(self, window: int, fine: int = FINE, patch: int = PATCH):
        window, fine, patch = int(window), int(fine), int(patch)
        if window < 1:
            raise ValueError(f"window must be at least 1 step, got {window}")
        if fine < 1 or patch < 1:
            raise ValueError(f"fine and patch must be at least 1 step, got fine={fine}, patch={patch}")
        self.window = window
        self.fine = min(fine, window)
        self.patch = patch
        if (window - self.fine) % patch:
            raise ValueError(f"window - fine ({window} - {self.fine}) must be a multiple of patch ({patch}): "
                             f"e.g. window={self.fine + patch * max(1, (window - self.fine) // patch)}")
        self.n_patches = (window - self.fine) // patch

    @property
    def n_tokens(self) -> int:
        return self.n_patches + self.fine

    def positions(self) -> np.ndarray:
        """Centre of each token, in steps from the window's first step (float32)."""
        coarse = np.arange(self.n_patches) * self.patch + (self.patch - 1) / 2.0
        fine = self.n_patches * self.patch + np.arange(self.fine)
        return np.concatenate([coarse, fine]).astype(np.float32)

    def tokens(self, x):
        """Tokens of windows x (n, window, features): a numpy array or a torch tensor, returned
        as the same kind (float32 means for numpy; the tensor's dtype for torch)."""
        numpy = isinstance(x, np.ndarray)
        if not numpy:
            import torch
        if (numpy or not torch.jit.is_tracing()) and x.shape[1] != self.window:   # (an exported graph fixes W)
            raise ValueError(f"windows of {x.shape[1]} steps given to a context of {self.window}")
        if not self.n_patches:
            return x
        split = self.n_patches * self.patch
        old = x[:, :split].reshape(-1, self.n_patches, self.patch, x.shape[-1])
        if numpy:
            return np.concatenate([old.mean(axis=2, dtype=np.float64).astype(x.dtype), x[:, split:]], axis=1)
        return torch.cat([old.mean(dim=2), x[:, split:]], dim=1)

    def __repr__(self) -> str:
        return f"Context(window={self.window}, fine={self.fine}, patch={self.patch})"


class StepTokens:
    """Tokens from per-step vectors, one step at a time, for ``n`` flights: ``context()`` gives
    the token means of the window ending at the next step without that step (n, n_tokens - 1,
    width) float32, the last token being the next step's own vector; ``push(v)`` adds that step
    (n, width). Before a flight's first step the window is padding whose vectors are zero (the
    step projections of the normalised padding, which is zero).

    State: the last ``fine`` vectors and the float64 prefix sums of the last ``window`` (a patch
    mean is the difference of two sums over ``patch``, rounded to float32, as the offline
    tokens: the mean in float64, then float32). Each ring is kept twice over, end to end, so
    that the last steps in order are one slice of it and a step copies nothing else."""

    def __init__(self, context: Context, n: int, width: int):
        self.layout = context
        self.k = 0                                                   # steps pushed
        self.recent = np.zeros((n, 2 * context.fine, width), dtype=np.float32)
        self.sums = np.zeros((n, 2 * context.window, width), dtype=np.float64)

    def context(self) -> np.ndarray:
        c, k = self.layout, self.k
        a = k % c.fine                                               # v[k - fine] sits at a (and a + fine)
        fine = self.recent[:, a + 1:a + c.fine]
        if not c.n_patches:
            return fine.copy()
        b = k % c.window                                             # S[k - window] sits at b (and b + window)
        s = self.sums[:, b:b + c.n_patches * c.patch + 1:c.patch]    # S[k - window + patch q], q = 0..n_patches
        out = np.empty((fine.shape[0], c.n_tokens - 1, fine.shape[2]), dtype=np.float32)
        out[:, :c.n_patches] = (s[:, 1:] - s[:, :-1]) / c.patch
        out[:, c.n_patches:] = fine
        return out

    def push(self, v: np.ndarray) -> None:
        c, k = self.layout, self.k
        i, j = k % c.window, (k - 1) % c.window
        self.sums[:, i] = self.sums[:, i + c.window] = self.sums[:, j] + v
        i = k % c.fine
        self.recent[:, i] = self.recent[:, i + c.fine] = v
        self.k = k + 1
