"""One training loop for every neural detector.

Mini-batches drawn with an explicit generator, AdamW, a cosine learning-rate decay,
early stopping on a held-out loss (the best state is kept), a progress bar, and all
randomness (initialisation, dropout, shuffling) derived from one seed inside a forked RNG
context, so the caller's global RNG state is untouched.

On CUDA, float32 is trained as IEEE float32 (``ieee_fp32``): cuDNN's default for convolutions and
recurrent layers is TF32 (a 10-bit mantissa) on Ampere and later GPUs. Measured on an H200 with
`quadformer benchmark --data <Model II, laplace, bias> --methods quadformer,lstm,cnn --device cuda`,
TF32 trained an LSTM and a CNN to test F1 0.66 and 0.61 where the CPU's reach 0.74 and 0.69;
IEEE float32 on the GPU gives 0.74 and 0.69, as the CPU does, in about the same time.
"""

from __future__ import annotations

import copy
import re
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
from torch import nn


DEVICES = ("auto", "cpu", "cuda")


def resolve_device(device: str) -> str:
    """The torch device to train on: ``auto`` is ``cuda`` when torch sees a CUDA device, else
    ``cpu``; ``cuda`` (or ``cuda:N``) without one is an error saying so."""
    name = str(device)
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cpu":
        return "cpu"
    if name == "cuda" or re.fullmatch(r"cuda:\d+", name):
        if not torch.cuda.is_available():
            raise ValueError(f"device: {name!r} requested but torch {torch.__version__} sees no CUDA device "
                             "(a CPU-only build, or no GPU on this machine); use --device cpu or auto")
        index = int(name.split(":")[1]) if ":" in name else 0
        if index >= torch.cuda.device_count():
            raise ValueError(f"device: {name!r} requested but torch sees {torch.cuda.device_count()} CUDA device(s)")
        return name
    raise ValueError(f"device: unknown choice {name!r}; choose from {', '.join(DEVICES)} (or cuda:N)")


@contextmanager
def ieee_fp32():
    """Inside: cuDNN's float32 convolutions and recurrent layers as IEEE float32, not TF32 (the
    previous settings restored after; no effect on a CPU)."""
    cudnn = torch.backends.cudnn
    if hasattr(cudnn, "conv") and hasattr(cudnn.conv, "fp32_precision"):
        settings = [(cudnn.conv, "fp32_precision", "ieee"), (cudnn.rnn, "fp32_precision", "ieee")]
    else:                               # torch before the fp32_precision settings
        settings = [(cudnn, "allow_tf32", False)]
    old = [getattr(where, name) for where, name, _ in settings]
    for where, name, value in settings:
        setattr(where, name, value)
    try:
        yield
    finally:
        for (where, name, _), value in zip(settings, old):
            setattr(where, name, value)


@dataclass(frozen=True)
class TrainConfig:
    epochs: int = 30
    batch_size: int = 256
    lr: float = 1e-3              # peak learning rate
    weight_decay: float = 1e-4
    patience: int = 10            # epochs without held-out improvement before stopping
    max_steps_per_epoch: int = 200
    seed: int = 0
    device: str = "cpu"
    progress: bool = False


@dataclass
class TrainResult:
    state: dict
    epochs_run: int
    best_epoch: int
    history: list[dict]


def train(build: Callable[[], nn.Module], loss_fn: Callable[[nn.Module, np.ndarray], torch.Tensor],
          n_train: int, n_holdout: int, cfg: TrainConfig) -> tuple[nn.Module, TrainResult]:
    """Train ``build()`` by minimising ``loss_fn(model, batch_indices)``.

    Training indices are 0..n_train-1; held-out indices are n_train..n_train+n_holdout-1
    (no held-out set: the training loss is monitored instead).
    """
    with torch.random.fork_rng(devices=[]), ieee_fp32():
        torch.manual_seed(cfg.seed)
        rng = np.random.default_rng(cfg.seed)
        model = build().to(cfg.device)
        opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
        steps = max(1, min(cfg.max_steps_per_epoch, int(np.ceil(n_train / cfg.batch_size))))
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=cfg.epochs * steps, eta_min=cfg.lr / 20)
        best, best_epoch, bad = np.inf, 0, 0
        best_state = copy.deepcopy(model.state_dict())
        history = []
        epochs = range(cfg.epochs)
        if cfg.progress:
            from tqdm.auto import tqdm
            epochs = tqdm(epochs, desc="train", unit="epoch", leave=False)
        epoch = -1
        for epoch in epochs:
            model.train()
            order = rng.permutation(n_train)
            total = 0.0
            for s in range(steps):
                idx = order[s * cfg.batch_size:(s + 1) * cfg.batch_size]
                if idx.size == 0:
                    break
                loss = loss_fn(model, idx)
                opt.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(model.parameters(), 5.0)
                opt.step()
                sched.step()
                total += float(loss.detach()) * idx.size
            train_loss = total / max(1, min(n_train, steps * cfg.batch_size))
            model.eval()
            with torch.no_grad():
                if n_holdout:
                    hold = np.arange(n_train, n_train + n_holdout)
                    held = np.mean([float(loss_fn(model, hold[i:i + 4096])) for i in range(0, n_holdout, 4096)])
                else:
                    held = train_loss
            history.append({"epoch": epoch, "train_loss": train_loss, "holdout_loss": float(held)})
            if held < best - 1e-6:
                best, best_epoch, bad = held, epoch, 0
                best_state = copy.deepcopy(model.state_dict())
            else:
                bad += 1
                if bad >= cfg.patience:
                    break
        model.load_state_dict(best_state)
        model.eval()
    return model, TrainResult(best_state, epoch + 1, best_epoch, history)
