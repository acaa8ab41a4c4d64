"""PCA reconstruction error on causal residue windows: a simple unsupervised anchor.

Each step's causal window of normalised residues (``detectors.windows``; the same features,
window, normalisation and tokens (``detectors.context``) as the learned detectors) is
flattened into one vector of its tokens. A PCA is
fitted on training windows not known to be attacked (unlabelled ones and those of labelled
clean steps; at most ``max_windows`` of them, drawn with the seed): their mean and the top
``n_components`` principal directions (SVD of the centred windows). Score of a step: the mean
squared residual of its window after projection onto that subspace, i.e. what the normal
subspace cannot explain. ``n_components`` is searched on validation flights like every
hyper-parameter; no label is needed to fit.
"""

from __future__ import annotations

import hashlib

import numpy as np
import pandas as pd

from quadformer.detectors.base import Detector, check_residues
from quadformer.detectors.context import FINE, PATCH, WINDOW, Context
from quadformer.detectors.registry import register
from quadformer.detectors.windows import Normalizer, Windows, WindowStream, input_features, window_scores


#: the last decomposition (key, mean, leading directions): tuning fits the same training
#: windows once per ``n_components`` of the grid, and the SVD of long windows dominates a fit
_LAST_SVD: list = []
_KEEP = 64     # leading directions kept for later fits with fewer components


def _principal_directions(Z: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean of Z's rows and its leading right singular vectors (at least k of them, fewer if Z
    has fewer), by a full SVD of the centred rows, reused for the same Z."""
    key = (Z.shape, hashlib.blake2b(np.ascontiguousarray(Z).tobytes(), digest_size=16).hexdigest())
    if _LAST_SVD and _LAST_SVD[0] == key and (_LAST_SVD[2].shape[0] >= k or _LAST_SVD[3]):
        return _LAST_SVD[1], _LAST_SVD[2]
    mean = Z.mean(axis=0)
    _, _, vt = np.linalg.svd(Z - mean, full_matrices=False)
    keep = max(k, _KEEP)
    _LAST_SVD[:] = [key, mean, vt[:keep].copy(), keep >= vt.shape[0]]
    return mean, _LAST_SVD[2]


@register("pca")
class PCADetector(Detector):
    param_grid = {"n_components": [2, 4, 8, 16, 32]}

    def __init__(self, window: int = WINDOW, n_components: int = 8, max_windows: int = 6000, seed: int = 0,
                 fine: int = FINE, patch: int = PATCH) -> None:
        self.window = window
        self.fine = fine
        self.patch = patch
        self.n_components = n_components
        self.max_windows = max_windows
        self.seed = seed

    @property
    def context(self) -> Context:
        return Context(self.window, self.fine, self.patch)

    def fit(self, X: pd.DataFrame, y: np.ndarray | None = None) -> "PCADetector":
        context = self.context     # checks window, fine and patch before any work
        self.features_ = input_features(X)
        self.normalizer_ = Normalizer().fit(check_residues(X, self.features_))
        win = Windows(X, self.features_, self.normalizer_, self.window)
        normal = np.arange(len(X)) if y is None else np.nonzero(np.asarray(y) != 1)[0]
        if normal.size == 0:
            raise ValueError("pca needs training steps not known to be attacked")
        rng = np.random.default_rng(self.seed)
        pick = np.sort(rng.choice(normal, min(len(normal), self.max_windows), replace=False))
        Z = win.tokens(pick, context).reshape(len(pick), -1).astype(np.float64)
        self.mean_, vt = _principal_directions(Z, int(self.n_components))
        self.components_ = vt[:int(self.n_components)]
        self.fitted_ = True
        return self

    def decision_function(self, X: pd.DataFrame) -> np.ndarray:
        self.check_fitted()
        return window_scores(self, X)

    def score_windows(self, windows: np.ndarray) -> tuple[np.ndarray, None]:
        """Mean squared reconstruction residual of normalised windows (n, W, features)."""
        return self.score_tokens(self.context.tokens(windows))

    def score_tokens(self, tokens: np.ndarray) -> tuple[np.ndarray, None]:
        """``score_windows`` of the windows whose tokens are given (n, tokens, features)."""
        z = tokens.reshape(len(tokens), -1).astype(np.float64) - self.mean_
        coef = z @ self.components_.T
        resid = z - coef @ self.components_
        return np.mean(resid * resid, axis=1), None

    def stream(self, n_flights: int = 1) -> WindowStream:
        return WindowStream(self, n_flights)

    def learned_state(self) -> dict:
        return {"features_": list(self.features_), "normalizer_": self.normalizer_.state(),
                "mean_": self.mean_.tolist(), "components_": self.components_.tolist(),
                **{k: v for k, v in vars(self).items()
                   if k.endswith("_") and not k.startswith("_")
                   and k not in ("features_", "normalizer_", "mean_", "components_", "fitted_")}}

    def load_state(self, state: dict) -> None:
        for k, v in state.items():
            if k == "normalizer_":
                self.normalizer_ = Normalizer.from_state(v)
            elif k in ("mean_", "components_"):
                setattr(self, k, np.asarray(v, dtype=np.float64))
            else:
                setattr(self, k, v)
        self.fitted_ = True
