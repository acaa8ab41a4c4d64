"""RBF support vector machine on causal residue windows.

Features of a step: the tokens of its normalised window (``detectors.context``: the last
steps one by one, earlier ones in patch means) flattened, plus per-feature mean, std, min and
max over the whole window. Trained on the labelled training flights, with at most
``max_windows`` windows (all attacked ones up to half of that, the rest clean), drawn with
the seed. Score: the SVM decision value.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from sklearn.svm import SVC

from quadformer.detectors.base import Detector, check_residues, labelled_split
from quadformer.detectors.context import FINE, PATCH, WINDOW, Context
from quadformer.detectors.registry import register
from quadformer.detectors.windows import Normalizer, Windows, WindowStream, input_features, window_scores


def _window_features(w: np.ndarray, context: Context) -> np.ndarray:
    tokens = context.tokens(w)
    return np.concatenate([tokens.reshape(len(w), -1), w.mean(1), w.std(1), w.min(1), w.max(1)], axis=1)


@register("svm")
class SVMDetector(Detector):
    param_grid = {"C": [1.0, 10.0]}

    def __init__(self, window: int = WINDOW, C: float = 1.0, gamma: str | float = "scale",
                 max_windows: int = 3000, seed: int = 0, fine: int = FINE, patch: int = PATCH) -> None:
        self.window = window
        self.fine = fine
        self.patch = patch
        self.C = C
        self.gamma = gamma
        self.max_windows = max_windows
        self.seed = seed

    @property
    def context(self) -> Context:
        return Context(self.window, self.fine, self.patch)

    def fit(self, X: pd.DataFrame, y: np.ndarray | None = None) -> "SVMDetector":
        context = self.context     # checks window, fine and patch before any work
        tr, ho = labelled_split(X, y, self.seed)
        rows = np.concatenate([tr, ho])          # no early stopping: use every labelled flight
        self.features_ = input_features(X)
        self.normalizer_ = Normalizer().fit(check_residues(X, self.features_))
        win = Windows(X, self.features_, self.normalizer_, self.window)
        yl = np.asarray(y)[rows] == 1
        rng = np.random.default_rng(self.seed)
        pos, neg = rows[yl], rows[~yl]
        n_pos = min(len(pos), self.max_windows // 2)
        n_neg = min(len(neg), self.max_windows - n_pos)
        pick = np.concatenate([rng.choice(pos, n_pos, replace=False), rng.choice(neg, n_neg, replace=False)])
        target = np.isin(pick, pos)
        if target.all() or not target.any():
            raise ValueError("svm needs attacked and clean steps among the labelled training flights")
        svc = SVC(kernel="rbf", C=self.C, gamma=self.gamma).fit(win.gather(pick, lambda w: _window_features(w, context)), target)
        # score with the decision function rebuilt from plain numbers, as after loading
        self.svc_ = _RBFDecision(svc.support_vectors_, svc.dual_coef_, svc.intercept_, svc._gamma)
        self.fitted_ = True
        return self

    def decision_function(self, X: pd.DataFrame) -> np.ndarray:
        self.check_fitted()
        return window_scores(self, X)

    def score_windows(self, windows: np.ndarray) -> tuple[np.ndarray, None]:
        """SVM decision values of normalised windows (n, W, features)."""
        return self.svc_.decision_function(_window_features(windows, self.context)), None

    def stream(self, n_flights: int = 1) -> WindowStream:
        return WindowStream(self, n_flights)

    def learned_state(self) -> dict:
        return {"features_": self.features_, "normalizer_": self.normalizer_.state(),
                **{k: v for k, v in vars(self).items()
                   if k.endswith("_") and k not in ("svc_", "normalizer_", "features_")},
                "svc_": self.svc_.state()}

    def load_state(self, state: dict) -> None:
        for k, v in state.items():
            if k == "normalizer_":
                self.normalizer_ = Normalizer.from_state(v)
            elif k == "svc_":
                self.svc_ = _RBFDecision(**v)
            else:
                setattr(self, k, v)
        self.fitted_ = True


class _RBFDecision:
    """The decision function of a fitted RBF SVC, rebuilt from plain numbers (no pickle)."""

    def __init__(self, support_vectors, dual_coef, intercept, gamma):
        self.sv = np.asarray(support_vectors, dtype=float)
        self.coef = np.asarray(dual_coef, dtype=float)[0]
        self.b = float(np.asarray(intercept)[0])
        self.gamma = float(gamma)

    def state(self) -> dict:
        return {"support_vectors": self.sv.tolist(), "dual_coef": [self.coef.tolist()],
                "intercept": [self.b], "gamma": self.gamma}

    def decision_function(self, Z: np.ndarray) -> np.ndarray:
        d2 = (Z * Z).sum(1)[:, None] - 2 * Z @ self.sv.T + (self.sv * self.sv).sum(1)[None, :]
        return np.exp(-self.gamma * np.maximum(d2, 0.0)) @ self.coef + self.b
