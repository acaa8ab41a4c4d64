"""Supervised window classifiers (CNN, LSTM) under the detector contract.

They learn from the labelled training flights only (label >= 0; the benchmark's budget,
``--label-fraction 1`` for all labels). A fifth of those flights (at least one, when there
are three or more) is held out for early stopping, so validation flights stay reserved for
hyper-parameters and thresholds. The score of a step is the logit of its causal window
(``window`` steps, summarised into tokens: ``detectors.context``).
Checkpoints: a JSON document (method, parameters, normaliser, threshold) plus a state dict
beside it (``.pt``), loaded with ``torch.load(..., weights_only=True)``.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pandas as pd
import torch
from torch import nn

from quadformer.detectors.base import Detector, check_residues, labelled_split
from quadformer.detectors.context import FINE, PATCH, WINDOW, Context
from quadformer.detectors.neural.cnn import CNN1d
from quadformer.detectors.neural.lstm import LSTMNet
from quadformer.detectors.neural.training import TrainConfig, train
from quadformer.detectors.registry import register
from quadformer.detectors.windows import AxisSymmetry, Normalizer, Windows, WindowStream, input_features, window_scores
from quadformer.io import atomic_write_bytes


class TorchCheckpoint:
    """Persistence of a network detector: learned attributes in the JSON document, the
    network's state dict beside it (``.pt``), read back with ``weights_only=True``.

    The device a network trained on does not change what is saved: the state dict is moved to
    the CPU and the document records ``device: cpu``, so a model trained on a GPU is saved,
    cached and loaded as one trained on the CPU."""

    def saved_params(self) -> dict[str, Any]:
        return {**self.get_params(), "device": "cpu"}

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
        # saved through a buffer: torch names the archive inside the file after the file it
        # writes to, and a temporary name would make two saves of one model differ
        buf = io.BytesIO()
        torch.save({k: v.detach().cpu() for k, v in self.model_.state_dict().items()}, buf)
        atomic_write_bytes(Path(path).with_suffix(".pt"), buf.getvalue())

    def load_extra(self, path: Path) -> None:
        wpath = Path(path).with_suffix(".pt")
        if not wpath.exists():
            raise FileNotFoundError(f"{wpath}: weights of {Path(path).name} are missing")
        model = self._build()
        try:
            # tensors only: a file holding pickled objects (code) is refused, never executed
            state = torch.load(wpath, map_location=self.device, weights_only=True)
        except Exception as e:   # UnpicklingError for objects, RuntimeError for corrupt files
            raise ValueError(f"{wpath}: not a plain tensor state dict ({type(e).__name__}: "
                             f"{str(e).splitlines()[0] if str(e) else ''})") from None
        if not isinstance(state, dict):
            raise ValueError(f"{wpath}: not a state dict")
        model.load_state_dict(state)
        self.model_ = model.to(self.device).eval()
        self.fitted_ = True


class WindowClassifier(TorchCheckpoint, Detector):
    network: ClassVar[type[nn.Module]]

    def __init__(self, window: int = WINDOW, epochs: int = 30, batch_size: int = 256, lr: float = 1e-3,
                 hidden: int = 32, augment: bool = True, seed: int = 0, device: str = "cpu",
                 progress: bool = False, fine: int = FINE, patch: int = PATCH) -> None:
        self.window = window
        self.fine = fine
        self.patch = patch
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

    @property
    def context(self) -> Context:
        return Context(self.window, self.fine, self.patch)

    def fit(self, X: pd.DataFrame, y: np.ndarray | None = None) -> "WindowClassifier":
        self.context     # checks window, fine and patch before any work
        tr, ho = labelled_split(X, y, self.seed)
        self.features_ = input_features(X)
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
        self.check_fitted()
        return window_scores(self, X)

    def score_windows(self, windows: np.ndarray) -> tuple[np.ndarray, None]:
        """Logits of normalised windows (n, W, features)."""
        with torch.no_grad():
            x = torch.from_numpy(np.ascontiguousarray(windows)).to(torch.device(self.device))
            return self.model_(x).double().cpu().numpy(), None

    def score_tokens(self, tokens: np.ndarray) -> tuple[np.ndarray, None]:
        """``score_windows`` of the windows whose tokens are given (n, tokens, features)."""
        with torch.no_grad():
            x = torch.from_numpy(np.ascontiguousarray(tokens)).to(torch.device(self.device))
            return self.model_(x, tokens=True).double().cpu().numpy(), None

    def stream(self, n_flights: int = 1) -> WindowStream:
        return WindowStream(self, n_flights)


@register("cnn")
class CNNDetector(WindowClassifier):
    """1D-CNN over the causal residue window."""
    param_grid = {"lr": [1e-3, 3e-3]}

    def _build(self) -> nn.Module:
        return CNN1d(len(self.features_), self.context, channels=self.hidden)


@register("lstm")
class LSTMDetector(WindowClassifier):
    """LSTM over the causal residue window."""
    param_grid = {"lr": [1e-3, 3e-3]}

    def __init__(self, window: int = WINDOW, epochs: int = 30, batch_size: int = 256, lr: float = 1e-3,
                 hidden: int = 64, augment: bool = True, seed: int = 0, device: str = "cpu",
                 progress: bool = False, fine: int = FINE, patch: int = PATCH) -> None:
        super().__init__(window, epochs, batch_size, lr, hidden, augment, seed, device, progress, fine, patch)

    def _build(self) -> nn.Module:
        return LSTMNet(len(self.features_), self.context, hidden=self.hidden)
