"""QUADFormer: the transformer attack detector and classifier.

Loss (semi-supervised), on each mini-batch of causal windows (a quarter drawn from all
training windows not known to be attacked, three quarters from labelled flights; all from
the former without supervision):

- Windows not known to end in an attack (most training windows are unlabelled and treated
  as mostly normal): reconstruction MSE of the normalised residues, plus the association
  discrepancy trained by the minimax strategy with stop-gradients in one backward pass,
  ``lambda_dis * [Dis(P, sg(S)) - Dis(sg(P), S)]``: the prior learns to match the series
  (minimise) while the series learns to move away from the local prior (maximise). Normal
  steps can spread their association and end far from the prior; attacked steps, whose
  informative neighbours are the other attacked steps, cannot. Weight ``lambda_dis`` = 0.1:
  the term is of the order of the reconstruction error of normalised inputs, and at weight 1
  its gradient (ascending on the series) reshaped the shared representation enough to cost
  the classifier 0.1 to 0.15 test F1 on bias attacks (quick profile); at 0.1 it shapes the
  statistic without that cost.
- Windows of labelled flights: cross-entropy of the per-step classifier (none / attack
  types), weight ``lambda_ce`` = 1, and a margin term ``lambda_margin`` = 0.1 times
  relu(margin + mean Dis(attacked) - mean Dis(normal)), which pushes the discrepancy of
  attacked steps below that of normal ones by ``margin``; small, because the classifier
  already carries the labels and the term only shapes the unsupervised statistic.

Windows are long (``window`` = 320 steps, 32 s) and enter the network as tokens
(``detectors.context``: the last ``fine`` steps one by one, earlier ones as patch means), so
the evidence of a spoof's onset stays in view while the filter absorbs it. The reconstruction
is that of the tokens; the classifier's cross-entropy and the margin apply to the last
``fine`` tokens, the only ones that carry one step's label each.

Score of step k (from the window ending at k, so causal): the classifier's attack log-odds
plus ``w_anomaly`` times the log of the discrepancy-weighted reconstruction error at k,
``err[k] * exp(-Dis[k] / tau)`` (tau: training median of Dis), relative to its training
median. ``w_anomaly`` (0, 0.5 or 1) is chosen on validation flights with the alarm rule: the
unsupervised statistic helps where labels are scarce and adds noise where the classifier
already separates the classes, and which holds depends on the configuration. Only the last
position of a window is needed, which scoring exploits; and each step is embedded (offline
also projected to the first layer's queries, keys and values) once, not once per window it
belongs to (``quadformer_steps``): offline scoring runs on batches of windows whose tokens are
read from the steps' projections, the stream (``StepStream``) keeps the window's step
embeddings as its state. Alarm rule (onset criterion): at least ``k`` of the last ``n``
scores above the threshold; the decision function is the k-th largest of the last n scores,
so ``score > threshold`` is exactly that rule. The onset is estimated by going back from
the alarm to where the score last rose above ``lower_`` (the 90th percentile of training
scores on normal steps).
"""

from __future__ import annotations

import hashlib
import inspect
from typing import Any

import numpy as np
import pandas as pd
import torch
from torch import nn

from quadformer.detectors.base import Detector, check_residues, labelled_split
from quadformer.detectors.context import FINE, PATCH, WINDOW, Context
from quadformer.detectors.neural.detector import TorchCheckpoint
# the alarm rule and the streams, also importable from here
from quadformer.detectors.neural.quadformer_alarms import (FLOOR, KofN, KofNStream, StepStream,  # noqa: F401
                                                           kth_of_last_n, onset_times)
from quadformer.detectors.neural.quadformer_net import QUADFormerNet, discrepancy, last_parts
from quadformer.detectors.neural.quadformer_steps import BATCH, StepNet, projected_batches
from quadformer.detectors.neural.training import TrainConfig, train
from quadformer.detectors.registry import register
from quadformer.detectors.windows import AxisSymmetry, Normalizer, Windows, input_features
from quadformer.estimator.schema import ATTACK_TYPES

#: windows per network call when scoring on the CPU: a call over a few dozen windows keeps the
#: attention's intermediate tensors in the processor's caches, where one over thousands
#: allocates, and first touches, hundreds of megabytes (offline scoring about twice as fast,
#: one thread; the CNN and LSTM gain nothing from it)
CPU_SCORE_BATCH = 64
CLASSES = ("none", *ATTACK_TYPES)   # the classifier's classes; a fitted model keeps its own (classes_)
W_ANOMALY = (0.0, 0.5, 1.0)     # weights of the unsupervised statistic in the score


class QUADFormer(TorchCheckpoint, Detector):
    param_grid: dict[str, list[Any]] = {}
    post_grid = {"k": [1, 2, 3], "n": [3, 5], "w_anomaly": list(W_ANOMALY)}

    def __init__(self, window: int = WINDOW, fine: int = FINE, patch: int = PATCH, d_model: int = 64,
                 heads: int = 4, layers: int = 2,
                 epochs: int = 15, batch_size: int = 64, lr: float = 1e-3, lambda_dis: float = 0.1,
                 lambda_ce: float = 1.0, lambda_margin: float = 0.1, margin: float = 0.5,
                 use_prior: bool = True, supervised: bool = True, use_discrepancy: bool = True,
                 prior_sigma: float | None = None,
                 k: int = 2, n: int = 3, w_anomaly: float = 1.0, augment: bool = True, steps_per_epoch: int = 60,
                 seed: int = 0, device: str = "cpu", progress: bool = False) -> None:
        self.window = window
        self.fine = fine
        self.patch = patch
        self.d_model = d_model
        self.heads = heads
        self.layers = layers
        self.epochs = epochs
        self.batch_size = batch_size
        self.lr = lr
        self.lambda_dis = lambda_dis
        self.lambda_ce = lambda_ce
        self.lambda_margin = lambda_margin
        self.margin = margin
        self.use_prior = use_prior
        self.supervised = supervised
        self.use_discrepancy = use_discrepancy
        self.prior_sigma = prior_sigma
        self.k = k
        self.n = n
        self.w_anomaly = w_anomaly
        self.augment = augment
        self.steps_per_epoch = steps_per_epoch
        self.seed = seed
        self.device = device
        self.progress = progress

    # -- model ------------------------------------------------------------------------------
    @property
    def _disc(self) -> bool:
        return self.use_prior and self.use_discrepancy

    @property
    def context(self) -> Context:
        return Context(self.window, self.fine, self.patch)

    def _build(self) -> nn.Module:
        return QUADFormerNet(len(self.features_), len(self.classes_), self.context, self.d_model, self.heads,
                             self.layers, use_prior=self.use_prior, prior_sigma=self.prior_sigma)

    def get_params(self, deep: bool = True) -> dict[str, Any]:
        sig = inspect.signature(QUADFormer.__init__)
        return {k: getattr(self, k) for k in sig.parameters if k != "self"}

    # -- training ---------------------------------------------------------------------------
    def fit(self, X: pd.DataFrame, y: np.ndarray | None = None) -> "QUADFormer":
        if self.k > self.n:
            raise ValueError(f"k ({self.k}) must not exceed n ({self.n})")
        if self.prior_sigma is not None and not (np.isfinite(self.prior_sigma) and self.prior_sigma > 0):
            raise ValueError(f"prior_sigma must be a positive number of steps or None, got {self.prior_sigma!r}")
        if float(self.w_anomaly) not in W_ANOMALY:
            raise ValueError(f"w_anomaly must be one of {W_ANOMALY}, got {self.w_anomaly!r}")
        fine = self.context.fine     # checks window, fine and patch
        self.features_ = input_features(X)
        self.classes_ = list(CLASSES)
        self.normalizer_ = Normalizer().fit(check_residues(X, self.features_))
        win = Windows(X, self.features_, self.normalizer_, self.window)
        n_rows = len(X)
        y = np.full(n_rows, -1) if y is None else np.asarray(y)
        cls = np.full(n_rows, -1, dtype=np.int64)
        known = y >= 0
        if self.supervised:
            if not known.any():
                raise ValueError("no labelled training flight: raise the label fraction or use quadformer-nosup")
            types = X["attack_type"].astype(str).to_numpy() if "attack_type" in X.columns else None
            cls[known & (y == 0)] = 0
            att = known & (y == 1)
            # an attacked step of unknown or unnamed type counts as the first attack class
            cls[att] = [self.classes_.index(t) if types is not None and t in self.classes_[1:] else 1 for t in
                        (types[att] if types is not None else np.full(att.sum(), self.classes_[1]))]
        unl = np.nonzero(~(known & (y == 1)))[0]       # windows treated as mostly normal
        lab_tr, lab_ho = labelled_split(X, y, self.seed) if self.supervised else (np.zeros(0, int),) * 2
        dev = torch.device(self.device)
        augment = AxisSymmetry(self.features_) if self.augment else None
        rng = np.random.default_rng(self.seed + 1)
        cls_t = torch.from_numpy(np.r_[cls, -1])         # index -1 -> padding -> ignored
        ce = nn.CrossEntropyLoss(ignore_index=-1)
        n_unlab = self.batch_size // 4 if self.supervised else self.batch_size   # the rest labelled
        holdout = lab_ho if len(lab_ho) else np.zeros(0, int)

        def loss_fn(model, idx):
            training = model.training
            if training:   # idx indexes nothing fixed: draw a mixed batch
                u = unl[rng.integers(len(unl), size=n_unlab)]
                lab = lab_tr[rng.integers(len(lab_tr), size=self.batch_size - n_unlab)] if self.supervised else u[:0]
            else:
                u, lab = holdout[idx - n_train_eff], holdout[idx - n_train_eff]
            rows = np.concatenate([u, lab])
            xb = torch.from_numpy(win[rows])
            if augment is not None and training:
                xb = augment(xb, rng)
            xb = xb.to(dev)
            out = model(xb)
            nu = len(u)
            loss = ((out["recon"][:nu] - out["tokens"][:nu]) ** 2).mean()
            # minimax: the prior descends the discrepancy, the series ascends it (one pass with
            # a gradient-reversed series). Its value is the discrepancy itself; the held-out
            # loss watched by early stopping leaves it out (reconstruction + CE + margin).
            if self._disc and training:
                loss = loss + self.lambda_dis * discrepancy(out["series"], out["priors"], "minimax")[:nu].mean()
            if self.supervised and len(lab):
                wr = win.rows(lab)[:, -fine:]      # the full-resolution tokens have one step each
                target = cls_t[torch.from_numpy(np.where(wr >= 0, wr, n_rows))].to(dev)
                logits = out["logits"][nu:, -fine:]
                loss = loss + self.lambda_ce * ce(logits.reshape(-1, logits.shape[-1]), target.reshape(-1))
                if self._disc and self.lambda_margin > 0:
                    d = discrepancy(out["series"], out["priors"])[nu:, -fine:]
                    att, nor = target > 0, target == 0
                    if att.any() and nor.any():
                        loss = loss + self.lambda_margin * torch.relu(self.margin + d[att].mean() - d[nor].mean())
            return loss

        n_train_eff = self.steps_per_epoch * self.batch_size
        cfg = TrainConfig(epochs=self.epochs, batch_size=self.batch_size, lr=self.lr, seed=self.seed,
                          device=self.device, progress=self.progress, max_steps_per_epoch=self.steps_per_epoch)
        self.model_, result = train(self._build, loss_fn, n_train_eff, len(holdout), cfg)
        self.history_ = result.history
        self.fitted_ = True
        # reference level of the unsupervised statistic, and the onset back-tracking level
        normal = np.nonzero(~(known & (y == 1)))[0]
        pick = np.random.default_rng(self.seed + 2).choice(normal, min(len(normal), 4000), replace=False)
        parts = self._parts(win, np.sort(pick))
        self.dis_scale_ = float(max(np.median(parts["dis"]), 1e-6)) if self._disc else 1.0
        self.anomaly_ref_ = float(np.median(self._anomaly(parts)))
        self.lower_ = {str(w): float(np.percentile(self._raw(parts, w), 90)) for w in W_ANOMALY}
        return self

    # -- scoring ----------------------------------------------------------------------------
    def _steps(self) -> StepNet:
        """The network scored from per-step projections (``quadformer_steps``), built once per
        fitted network (not saved: derived from its weights)."""
        net = self.__dict__.get("_step_net")
        if net is None or net.net is not self.model_:
            net = self._step_net = StepNet(self.model_, self._disc)
        return net

    def _parts(self, win: Windows, idx: np.ndarray) -> dict[str, np.ndarray]:
        """Per-step ingredients of the score for windows idx (their last position), from per-step
        projections (``quadformer_steps``): each step of a chunk projected once, the network on
        batches of windows. Equals ``_window_parts`` of the gathered windows to float32 rounding."""
        idx = np.asarray(idx)
        net = self._steps()
        dev = torch.device(self.device)
        out = {k: np.empty(len(idx), dtype=np.int64 if k == "type" else np.float64)
               for k in ("err", "dis", "p_attack", "type")}
        batch = BATCH if dev.type == "cpu" else 4096
        with torch.inference_mode():
            for pos, tokens, last in projected_batches(net, win, idx, self.context, batch):
                for k, v in net.score(tokens, last).items():
                    out[k][pos] = v.cpu().numpy()
        return out

    def _window_parts(self, windows: np.ndarray, tokens: bool = False) -> dict[str, np.ndarray]:
        """Score ingredients of the last position of normalised windows (n, W, features), or of
        the windows whose tokens are given (``tokens=True``: (n, T, features)): the network on
        each whole window (``score_windows``)."""
        with torch.no_grad():
            xb = torch.from_numpy(np.ascontiguousarray(windows)).to(torch.device(self.device))
            step = CPU_SCORE_BATCH if xb.device.type == "cpu" else max(1, len(xb))
            chunks = [last_step_parts(self.model_, xb[i:i + step], self._disc, tokens=tokens)
                      for i in range(0, len(xb), step)] or [last_step_parts(self.model_, xb, self._disc, tokens)]
            parts = {k: torch.cat([c[k] for c in chunks]) for k in chunks[0]}
            return {k: (v if k == "type" else v.double()).cpu().numpy() for k, v in parts.items()}

    def score_windows(self, windows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Raw scores (before the k-of-n rule) and predicted attack types of normalised windows
        (n, W, features), the network run on each whole window (the reference the step-wise
        scoring of ``raw_scores`` and ``stream`` equals to float32 rounding)."""
        parts = self._window_parts(windows)
        return self._raw(parts), np.array(self.classes_, dtype=object)[parts["type"].astype(int)]

    def score_step(self, x: np.ndarray, context: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One step of windows scored incrementally: normalised last steps x (n, features) and the
        token means of the embeddings of the windows' earlier steps (n, T-1, d_model) -> raw
        scores, attack type names and the steps' embeddings (n, d_model) float32 (``StepStream``)."""
        net = self._steps()
        dev = torch.device(self.device)
        with torch.inference_mode():
            p = net(torch.from_numpy(x).to(dev), torch.from_numpy(context).to(dev))
            parts = {k: v.cpu().numpy() for k, v in p.items()}
        raw = self._raw({k: parts[k].astype(np.float64) for k in ("err", "dis", "p_attack")})
        return raw, np.array(self.classes_, dtype=object)[parts["type"]], parts["embedding"]

    def _anomaly(self, parts: dict[str, np.ndarray]) -> np.ndarray:
        """Log of the discrepancy-weighted reconstruction error, err * exp(-Dis / tau), tau the
        training median of the discrepancy (small discrepancy: association like the local prior)."""
        log_a = np.log(np.maximum(parts["err"], 1e-12))
        if self._disc:
            log_a = log_a - parts["dis"] / self.dis_scale_
        return log_a

    def _raw(self, parts: dict[str, np.ndarray], w_anomaly: float | None = None) -> np.ndarray:
        w = self.w_anomaly if w_anomaly is None else w_anomaly
        if not self.supervised:
            w = 1.0   # the unsupervised statistic is all there is
        s = w * (self._anomaly(parts) - self.anomaly_ref_)
        if self.supervised:
            p = np.clip(parts["p_attack"], 1e-6, 1 - 1e-6)
            s = s + np.log(p) - np.log1p(-p)
        return s

    def raw_scores(self, X: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
        """Per-step raw score and predicted attack type index (before the k-of-n rule).

        The last result is cached (shared with ``with_post`` copies), so tuning the alarm rule
        does not run the network again."""
        self.check_fitted()
        cols = [c for c in ["flight_id", *self.features_] if c in X.columns]
        key = hashlib.blake2b(np.ascontiguousarray(X[cols].to_numpy(dtype=float)).tobytes(),
                              digest_size=16).hexdigest()     # content, not identity
        cache = self.__dict__.setdefault("_cache", {})
        if cache.get("key") != key:
            win = Windows(X, self.features_, self.normalizer_, self.window)
            cache.update(key=key, parts=self._parts(win, np.arange(len(win))))
        parts = cache["parts"]
        return self._raw(parts), parts["type"].astype(int)

    def with_post(self, **post: Any) -> "QUADFormer":
        """A copy with another alarm rule or score weight, sharing the fitted network and its
        cached per-step score ingredients: tuning the alarm rule scores the network once."""
        self.__dict__.setdefault("_cache", {})
        return super().with_post(**post)

    def decision_function(self, X: pd.DataFrame) -> np.ndarray:
        raw, _ = self.raw_scores(X)
        return kth_of_last_n(raw, X, self.k, self.n)

    def clear_cache(self) -> None:
        """Forget the cached raw scores (timings)."""
        self.__dict__.pop("_cache", None)

    def predict_type(self, X: pd.DataFrame) -> np.ndarray:
        """Predicted attack type at each step (meaningful where an alarm is raised)."""
        _, t = self.raw_scores(X)
        return np.array(self.classes_, dtype=object)[t]

    def onset_times(self, X: pd.DataFrame, alarms: np.ndarray) -> list[tuple[Any, float, float]]:
        """(flight, alarm time, estimated onset time) for each alarm run."""
        raw, _ = self.raw_scores(X)
        return onset_times(X, alarms, raw, self._lower())

    @property
    def onset_level_(self) -> float:
        """The raw-score level an alarm is back-tracked to for its onset (``onset_times``)."""
        return self._lower()

    def _lower(self) -> float:
        """Onset back-tracking level: the 90th percentile of training scores on normal steps
        (for the configured ``w_anomaly``)."""
        return float(self.lower_[str(float(self.w_anomaly) if self.supervised else 1.0)])

    def stream(self, n_flights: int = 1) -> "StepStream":
        """Online scoring, one network call per GPS step for all flights, from per-step
        embeddings (``StepStream``); equal to ``decision_function`` to float32 rounding."""
        return StepStream(self, n_flights, self.score_step, self.normalizer_, self._steps().width)


def last_step_parts(model: nn.Module, xb: torch.Tensor, disc: bool, tokens: bool = False) -> dict[str, torch.Tensor]:
    """Score ingredients of the last position of normalised windows xb (n, W, features) (or of
    their tokens, ``tokens=True``), the network run on each whole window, as float32 tensors
    (type: int64): reconstruction error, association discrepancy (zero without it), attack
    probability and the most likely attack class (``quadformer_net.last_parts``). Shared by
    ``score_windows`` and the exported graph of whole windows (``detectors.export``)."""
    o = model(xb, last_only=True, tokens=tokens)
    dis = discrepancy(o["series"], o["priors"])[:, -1] if disc else None
    return last_parts(o["recon"][:, -1], o["logits"][:, -1], o["tokens"][:, -1], dis)


def _variant(name: str, doc: str, **fixed: Any) -> type[QUADFormer]:
    class Variant(QUADFormer):
        __doc__ = doc

        def __init__(self, **kw: Any) -> None:
            super().__init__(**{**fixed, **kw})

        def get_params(self, deep: bool = True) -> dict[str, Any]:
            p = QUADFormer.get_params(self, deep)
            return {k: v for k, v in p.items() if k not in fixed}

    Variant.__name__ = Variant.__qualname__ = "QUADFormer_" + name.split("-")[-1]
    return register(name, default=False)(Variant)


register("quadformer")(QUADFormer)
_variant("quadformer-noprior", "Ablation: a fixed prior, no learned one: the prior association is a Gaussian "
         "kernel of fixed width (sigma = 2 GPS steps, the same for every head and position), so the "
         "association discrepancy is still trained and scored, against a prior that learns nothing. "
         "(Without any prior branch there would be no discrepancy and the variant would train the "
         "network of quadformer-nodisc.)", prior_sigma=2.0)
_variant("quadformer-nosup", "Ablation: no supervised terms (no labels used).", supervised=False)
_variant("quadformer-nodisc", "Ablation: no discrepancy term in loss or score.", use_discrepancy=False)
