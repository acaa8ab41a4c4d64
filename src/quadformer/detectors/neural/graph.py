"""The network detectors' ONNX graphs (``detectors.export``): raw residue windows -> score
(and, for QUADFormer, attack class), the feature normalisation inside the graph; for
QUADFormer also the streaming graph, one step plus the state of the window before it.

Apart from ``export``, so that opening a saved model (``export.load_model``) does not load
torch; ``export.export_onnx`` builds these."""

from __future__ import annotations

import copy

import numpy as np
import torch
from torch import nn

from quadformer.detectors.neural.detector import WindowClassifier
from quadformer.detectors.neural.quadformer import QUADFormer, last_step_parts
from quadformer.detectors.neural.quadformer_steps import StepNet
from quadformer.detectors.windows import Normalizer

__all__ = ["Asinh", "LogitGraph", "Normalise", "QUADFormerGraph", "QUADFormerStepGraph", "centre"]


class Asinh(torch.autograd.Function):
    """asinh, exported as ``sign(x) * log(a + sqrt(a^2 + 1))`` with ``a = min(|x|, 1e18)``
    (so that a^2 cannot overflow: inputs beyond 1e18 read as 1e18, asinh 42.1).
    onnxruntime's ``Asinh`` kernel is scalar: on a 320-step window of 65 features it took
    about 0.6 ms, half of a QUADFormer step; Log, Sqrt and the rest are vectorised. Within
    2e-7 absolute of float32 ``asinh`` (the formula loses relative, not absolute, precision
    near zero)."""

    @staticmethod
    def forward(ctx, x):
        return torch.asinh(x)

    @staticmethod
    def symbolic(g, x):
        def const(v):
            return g.op("Constant", value_t=torch.tensor(v, dtype=torch.float32))

        a = g.op("Min", g.op("Abs", x), const(1e18))
        y = g.op("Log", g.op("Add", a, g.op("Sqrt", g.op("Add", g.op("Mul", a, a), const(1.0)))))
        return g.op("Mul", g.op("Sign", x), y)


class Normalise(nn.Module):
    """``Normalizer.transform`` in float32: raw residues -> the network's inputs."""

    def __init__(self, normalizer: Normalizer):
        super().__init__()
        self.register_buffer("centre", torch.from_numpy(centre(normalizer)))
        self.register_buffer("scale", torch.from_numpy(np.asarray(normalizer.std_, dtype=np.float32)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return Asinh.apply((x - self.centre) / self.scale)


class LogitGraph(nn.Module):
    """CNN / LSTM: raw windows -> the window's logit (float64)."""

    def __init__(self, det: WindowClassifier):
        super().__init__()
        self.norm = Normalise(det.normalizer_)
        self.net = copy.deepcopy(det.model_).cpu().eval()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(self.norm(x)).double()


class QUADFormerGraph(nn.Module):
    """QUADFormer: raw windows -> (raw score of the last step (float64), attack class index).
    The score is ``QUADFormer._raw`` on ``last_step_parts`` (float32 network, float64 tail)."""

    def __init__(self, det: QUADFormer):
        super().__init__()
        self.norm = Normalise(det.normalizer_)
        self.net = copy.deepcopy(det.model_).cpu().eval()
        self.disc = det._disc
        self.supervised = det.supervised
        self.w = float(det.w_anomaly) if det.supervised else 1.0
        self.ref = float(det.anomaly_ref_)
        self.dis_scale = float(det.dis_scale_)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        parts = last_step_parts(self.net, self.norm(x), self.disc)
        return self.raw(parts), parts["type"]

    def raw(self, parts: dict[str, torch.Tensor]) -> torch.Tensor:
        """``QUADFormer._raw`` of the score ingredients, in float64."""
        log_a = torch.log(torch.clamp_min(parts["err"].double(), 1e-12))     # QUADFormer._anomaly
        if self.disc:
            log_a = log_a - parts["dis"].double() / self.dis_scale
        s = self.w * (log_a - self.ref)
        if self.supervised:
            p = torch.clamp(parts["p_attack"].double(), 1e-6, 1 - 1e-6)
            s = s + torch.log(p) - torch.log1p(-p)
        return s


class QUADFormerStepGraph(QUADFormerGraph):
    """QUADFormer's streaming graph: (raw residues of a window's last step (batch, features),
    the token means of the embeddings of the window's earlier steps (batch, T-1, d_model)) ->
    (its raw score (float64), attack class index, the step's embedding (batch, d_model)), the
    network scored from per-step embeddings (``quadformer_steps.StepNet``). The state a window
    needs from its earlier steps is passed in, the new step's part of it passed out."""

    def __init__(self, det: QUADFormer):
        super().__init__(det)
        self.steps = StepNet(self.net, self.disc)

    def forward(self, x: torch.Tensor, context: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        parts = self.steps(self.norm(x), context)
        return self.raw(parts), parts["type"], parts["embedding"]


def centre(normalizer: Normalizer) -> np.ndarray:
    return np.asarray(normalizer.mean_, dtype=np.float32)
