"""Supervised window classifiers (CNN, LSTM) under the detector contract.

They learn from the labelled training flights only (label >= 0; the benchmark's budget,
``--label-fraction 1`` for all labels). A fifth of those flights (at least one, when there
are three or more) is held out for early stopping, so validation flights stay reserved for
hyper-parameters and thresholds. The score of a step is the logit of its causal window.
Checkpoints: a JSON document (method, parameters, normaliser, threshold) plus a state dict
beside it (``.pt``), loaded with ``torch.load(..., weights_only=True)``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pandas as pd
import torch
from torch import nn

from quadformer.detectors.base import Detector, labelled_split
from quadformer.detectors.neural.cnn import CNN1d
from quadformer.detectors.neural.lstm import LSTMNet
from quadformer.detectors.neural.training import TrainConfig, train
from quadformer.detectors.registry import register
from quadformer.detectors.windows import RESIDUE_FEATURES, AxisSymmetry, Normalizer, Windows


class TorchCheckpoint:
    """Persistence of a network detector: learned attributes in the JSON document, the
    network's state dict beside it (``.pt``), read back with ``weights_only=True``."""

    def learned_state(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for k, v in vars(self).items():
            if k.endswith("_") and not k.startswith("_") and k != "model_":
                out[k] = v.state() if isinstance(v, Normalizer) else v.tolist() if isinstance(v, np.ndarray) else v
        return out

    def load_state(self, state: dict[str, Any]) -> None:
        for k, v in state.items():
            setattr(self, k, Normalizer.from_state(v) if k == "normalizer_" else v)

    def save_extra(self, path: Path) -> None:
        torch.save(self.model_.state_dict(), Path(path).with_suffix(".pt"))

    def load_extra(self, path: Path) -> None:
        wpath = Path(path).with_suffix(".pt")
        if not wpath.exists():
            raise FileNotFoundError(f"{wpath}: weights of {Path(path).name} are missing")
        model = self._build()
        model.load_state_dict(torch.load(wpath, map_location=self.device, weights_only=True))
        self.model_ = model.to(self.device).eval()
        self.fitted_ = True


class WindowClassifier(TorchCheckpoint, Detector):
    network: ClassVar[type[nn.Module]]

    def __init__(self, window: int = 32, epochs: int = 30, batch_size: int = 256, lr: float = 1e-3,
                 hidden: int = 32, augment: bool = True, seed: int = 0, device: str = "cpu",
                 progress: bool = False) -> None:
        self.window = window
        self.augment = augment
        self.epochs = epochs
        self.batch_size = batch_size
        self.lr = lr
        self.hidden = hidden
        self.seed = seed
        self.device = device
        self.progress = progress

    def _build(self) -> nn.Module:
        raise NotImplementedError

    def fit(self, X: pd.DataFrame, y: np.ndarray | None = None) -> "WindowClassifier":
        tr, ho = labelled_split(X, y, self.seed)
        self.features_ = [c for c in RESIDUE_FEATURES if c in X.columns]
        from quadformer.detectors.base import check_residues
        self.normalizer_ = Normalizer().fit(check_residues(X, self.features_))   # all training rows
        win = Windows(X, self.features_, self.normalizer_, self.window)
        rows = np.concatenate([tr, ho])
        target = torch.as_tensor(np.asarray(y)[rows] == 1, dtype=torch.float32)
        pos = float(target[: len(tr)].sum())
        pos_weight = torch.tensor((len(tr) - pos) / max(pos, 1.0))
        dev = torch.device(self.device)
        bce = nn.BCEWithLogitsLoss(pos_weight=pos_weight.to(dev))

        augment = AxisSymmetry(self.features_) if self.augment else None
        aug_rng = np.random.default_rng(self.seed + 1)

        def loss_fn(model, idx):
            xb = torch.from_numpy(win[rows[idx]])
            if augment is not None and model.training:
                xb = augment(xb, aug_rng)
            return bce(model(xb.to(dev)), target[idx].to(dev))

        cfg = TrainConfig(epochs=self.epochs, batch_size=self.batch_size, lr=self.lr, seed=self.seed,
                          device=self.device, progress=self.progress)
        self.model_, result = train(self._build, loss_fn, len(tr), len(ho), cfg)
        self.history_ = result.history
        self.fitted_ = True
        return self

    def decision_function(self, X: pd.DataFrame) -> np.ndarray:
        self._check_fitted()
        win = Windows(X, self.features_, self.normalizer_, self.window)
        out = np.empty(len(win), dtype=np.float64)
        dev = torch.device(self.device)
        with torch.no_grad():
            for i in range(0, len(win), 4096):
                idx = np.arange(i, min(i + 4096, len(win)))
                out[idx] = self.model_(torch.from_numpy(win[idx]).to(dev)).double().cpu().numpy()
        return out

    def batch_stream(self, n_flights: int) -> "WindowBatchStream":
        return WindowBatchStream(self, n_flights)


class WindowBatchStream:
    """A window classifier online over n flights stepped together:
    ``update(residues (n, features)) -> (scores (n,), alarms (n,), None)``; a ring buffer of the
    last W normalised residues per flight (zeros before the first step, as offline)."""

    def __init__(self, det: WindowClassifier, n_flights: int):
        det._check_fitted()
        self.det = det
        self.buf = np.zeros((n_flights, det.window, len(det.features_)), dtype=np.float32)

    def update(self, residues: np.ndarray):
        d = self.det
        v = np.asarray(residues, dtype=float)
        if v.shape != self.buf.shape[::2] or not np.isfinite(v).all():
            raise ValueError(f"residues must be {len(self.buf)} rows of {len(d.features_)} finite values "
                             f"({', '.join(d.features_)})")
        self.buf[:, :-1] = self.buf[:, 1:]
        self.buf[:, -1] = d.normalizer_.transform(v)
        with torch.no_grad():
            score = d.model_(torch.from_numpy(self.buf).to(torch.device(d.device))).double().cpu().numpy()
        thr = getattr(d, "threshold_", None)
        return score, (score > thr if thr is not None else np.zeros(len(score), bool)), None

@register("cnn")
class CNNDetector(WindowClassifier):
    """1D-CNN over the causal residue window."""
    param_grid = {"lr": [1e-3, 3e-3]}

    def _build(self) -> nn.Module:
        return CNN1d(len(self.features_), channels=self.hidden)


@register("lstm")
class LSTMDetector(WindowClassifier):
    """LSTM over the causal residue window."""
    param_grid = {"lr": [1e-3, 3e-3]}

    def __init__(self, window: int = 32, epochs: int = 30, batch_size: int = 256, lr: float = 1e-3,
                 hidden: int = 64, augment: bool = True, seed: int = 0, device: str = "cpu",
                 progress: bool = False) -> None:
        super().__init__(window, epochs, batch_size, lr, hidden, augment, seed, device, progress)

    def _build(self) -> nn.Module:
        return LSTMNet(len(self.features_), hidden=self.hidden)
