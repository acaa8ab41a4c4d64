"""Network detectors as ONNX graphs, scored with onnxruntime.

``export_onnx(detector, "model.onnx")`` writes two files, each atomically:

- ``model.onnx``: a graph from RAW residue windows ``residues`` (batch, W, features) float32
  (dynamic batch; columns in the order of ``features``, oldest step first) to
  ``score`` (batch,) float64 and, for QUADFormer, ``attack_class`` (batch,) int64. Inside:
  the feature normalisation (``windows.Normalizer``: ``asinh((x - centre) / scale)``, in
  float32), the window's tokens (``detectors.context``: patch means of the older steps, the
  last ``fine`` steps as they are) and the network; for CNN and LSTM the score is the logit of the window, for
  QUADFormer it is the raw score of the window's last step (classifier log-odds plus
  ``w_anomaly`` times the discrepancy-weighted reconstruction term relative to its training
  reference, ``QUADFormer._raw``, in float64) and ``attack_class`` the index of the most
  likely attack class in ``classes``.
- for QUADFormer, ``model.stream.onnx``, the streaming graph (format version 2): one GPS step
  at a time without recomputing the window's start. Inputs ``residues`` (batch, features), the
  raw residues of the window's last step, and ``context`` (batch, T-1, d_model) float32, the
  token means of the embeddings of the window's earlier steps; outputs ``score`` and
  ``attack_class`` as above and ``embedding`` (batch, d_model) float32, the new step's
  embedding (``detectors.neural.quadformer_steps``: a token's embedding is linear in its
  steps, so each step is embedded once, without the bias and positional encoding, which the
  graph adds per token). The state, kept by the runtime per flight (``context.StepTokens``):
  the last ``fine`` embeddings and the float64 prefix sums of the last ``window``; a coarse
  token is the difference of two prefix sums over ``patch`` steps (float64, then float32), a
  fine token one step's embedding; zero before the flight's first step (the padding embeds to
  zero).
- ``model.onnx.json`` (the graph's name plus ``.json``, so that it never replaces a saved
  model's ``model.json``): what a runtime needs beside the graphs (``_metadata``), with each
  graph's SHA-256.

What stays outside the graphs: the windowing (a ring buffer over GPS steps online, or the
streaming graph's state) and, for QUADFormer, the k-of-n alarm rule over the last n raw scores
(also a ring buffer over steps). Before a flight's first step, a window is padded with
``padding`` (raw values): the normaliser's centre, which the graph maps to exactly zero, the
padding of the offline normalised windows. Format version 1 (no streaming graph) still loads;
its stream scores whole windows.

``detectors.onnx_runtime`` scores the files: ``OnnxDetector`` honours the detector contract
(offline ``decision_function``, ``stream``, the saved alarm rule); ``load_model(path, runtime)``
opens a saved model with PyTorch or onnxruntime (both still importable from here).
"""

from __future__ import annotations

import hashlib
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from quadformer.detectors.base import Detector
from quadformer.detectors.onnx_files import (CONTEXT, FORMAT, FORMAT_VERSION, INPUT, OPSET, RUNTIMES, export_files,
                                             meta_path, stream_path)
from quadformer.io import PACKAGES, atomic_path, package_versions, write_json

#: the export's files and runtimes (``detectors.onnx_files``) are named here too, where they were first
__all__ = ["FORMAT", "FORMAT_VERSION", "OPSET", "RUNTIMES", "export_files", "export_onnx", "exportable"]


# -- the graph (torch, loaded by export_onnx: detectors.neural.graph) ------------------------
def exportable(detector: Detector) -> bool:
    """Whether ``export_onnx`` takes this detector (the network detectors)."""
    from quadformer.detectors.neural import QUADFormer, WindowClassifier

    return isinstance(detector, (WindowClassifier, QUADFormer))


def export_onnx(detector: Detector, path: str | Path, *, opset: int = OPSET) -> Path:
    """Write a fitted network detector as ``path`` (an ONNX graph, name ending in ``.onnx``)
    and its metadata as ``path`` + ``.json``; returns ``path``. See the module docstring."""
    import torch

    from quadformer.detectors.neural.graph import LogitGraph, QUADFormerGraph, QUADFormerStepGraph, centre
    from quadformer.detectors.neural.quadformer import QUADFormer

    if not exportable(detector):
        raise ValueError(f"{detector.name}: only the network detectors (cnn, lstm, quadformer and its variants) "
                         "export to ONNX; the classical statistics and the SVM are plain numbers in their "
                         "saved JSON already")
    detector.check_fitted()
    path = Path(path)
    if path.suffix != ".onnx":
        raise ValueError(f"{path}: an exported graph's name ends in .onnx")
    quad = isinstance(detector, QUADFormer)
    graph = (QUADFormerGraph if quad else LogitGraph)(detector).eval()
    pad = centre(detector.normalizer_)
    example = torch.from_numpy(np.tile(pad, (2, detector.window, 1)))
    outputs = ["score", "attack_class"] if quad else ["score"]
    digest = _export(graph, (example,), path, [INPUT], outputs, opset)
    stream = None
    if quad:
        step = QUADFormerStepGraph(detector).eval()
        ctx = detector.context
        example = (torch.from_numpy(np.tile(pad, (2, 1))), torch.zeros(2, ctx.n_tokens - 1, step.steps.width))
        spath = stream_path(path)
        stream = {"graph": spath.name, "sha256": _export(step, example, spath, [INPUT, CONTEXT],
                                                         [*outputs, "embedding"], opset),
                  "width": int(step.steps.width)}
    write_json(meta_path(path), _metadata(detector, digest, opset, stream))
    return path


def _export(graph, example: tuple, path: Path, inputs: list[str], outputs: list[str], opset: int) -> str:
    """Write ``graph`` traced on ``example`` as ONNX at ``path`` (atomically, batch dynamic);
    returns the file's SHA-256."""
    import torch

    with atomic_path(path) as tmp, warnings.catch_warnings():
        # The TorchScript-based exporter is the one that needs no extra package (the
        # torch.export-based one needs onnxscript). Notes that say nothing about these graphs,
        # silenced here only: its deprecation notice; the tracer on unpacking the fixed-size
        # (q, k, v) stack and on the LSTM's shape checks (window and features are fixed); the
        # LSTM batch-size caution (its initial states are built from the input's batch size,
        # and the tests score batches of 1 to 64).
        warnings.filterwarnings("ignore", message=".*legacy TorchScript-based ONNX export", category=DeprecationWarning)
        warnings.filterwarnings("ignore", message="The feature will be removed", category=DeprecationWarning)
        warnings.filterwarnings("ignore", message="Iterating over a tensor", category=torch.jit.TracerWarning)
        warnings.filterwarnings("ignore", message="Converting a tensor to a Python boolean",
                                category=torch.jit.TracerWarning, module=r"torch\.nn\.modules\.rnn")
        warnings.filterwarnings("ignore", message="Exporting a model to ONNX with a batch_size other than 1",
                                category=UserWarning)
        torch.onnx.export(graph, example, str(tmp), input_names=inputs, output_names=outputs,
                          dynamic_axes={name: {0: "batch"} for name in [*inputs, *outputs]},
                          opset_version=opset, dynamo=False)
        return hashlib.sha256(tmp.read_bytes()).hexdigest()


def _metadata(detector: Detector, graph_sha256: str, opset: int = OPSET,
              stream: dict[str, Any] | None = None) -> dict[str, Any]:
    """The JSON document beside an exported graph (``stream``: the streaming graph's file
    name, SHA-256 and state width, QUADFormer only)."""
    from quadformer.detectors.neural.graph import centre as graph_centre
    from quadformer.detectors.neural.quadformer import FLOOR, QUADFormer

    quad = isinstance(detector, QUADFormer)
    centre = graph_centre(detector.normalizer_)
    threshold = getattr(detector, "threshold_", None)
    budget = getattr(detector, "budget_threshold_", None)
    rule = {"threshold": threshold, "budget_threshold": budget, "k": None, "n": None,
            "in_graph": False, "rule": "alarm where score > threshold"}
    if quad:
        rule.update(k=int(detector.k), n=int(detector.n), floor=FLOOR,
                    rule="alarm where at least k of the flight's last n scores exceed threshold: the "
                         "k-th largest of the last n scores > threshold (floor before the flight's k-th step)")
    n_feat = len(detector.features_)
    doc: dict[str, Any] = {
        "format": FORMAT, "format_version": FORMAT_VERSION, "method": detector.name,
        "graph_sha256": graph_sha256, "opset": opset,
        "features": list(detector.features_), "window": int(detector.window),
        "context": {"window": int(detector.window), "fine": int(detector.context.fine),
                    "patch": int(detector.context.patch),
                    "tokens": "inside the graph: means of patch steps, then the last fine steps"},
        "input": {"name": INPUT, "shape": ["batch", int(detector.window), n_feat], "dtype": "float32",
                  "values": "raw residues, columns in the order of features, oldest step first"},
        "outputs": {"score": {"shape": ["batch"], "dtype": "float64",
                              "values": "raw score of the window's last step, before the k-of-n rule" if quad
                              else "logit of the window (the detector's score)"}},
        "padding": [float(v) for v in centre],
        "normalizer": {"centre": [float(v) for v in centre],
                       "scale": [float(v) for v in np.asarray(detector.normalizer_.std_, dtype=np.float32)],
                       "transform": "asinh((x - centre) / scale), float32"},
        "alarm_rule": rule,
        "classes": list(detector.classes_) if quad else None,
    }
    if quad:
        doc["outputs"]["attack_class"] = {"shape": ["batch"], "dtype": "int64",
                                          "values": "index in classes of the most likely attack type"}
    if stream is not None:
        ctx = detector.context
        width = stream["width"]
        doc["stream"] = {
            "graph": stream["graph"], "graph_sha256": stream["sha256"],
            "inputs": {INPUT: {"shape": ["batch", n_feat], "dtype": "float32",
                               "values": "raw residues of the window's last step, columns in the order of features"},
                       CONTEXT: {"shape": ["batch", ctx.n_tokens - 1, width], "dtype": "float32",
                                 "values": "the window's tokens before its last step, each the mean of the "
                                           "embeddings of its steps (the coarse tokens first, oldest first)"}},
            "outputs": {"score": doc["outputs"]["score"], "attack_class": doc["outputs"]["attack_class"],
                        "embedding": {"shape": ["batch", width], "dtype": "float32",
                                      "values": "the embedding of the last step, to be kept in the state"}},
            "state": "per flight: the embeddings of the last fine steps and the float64 prefix sums of the "
                     "embeddings over the last window steps, zero before the flight's first step (the "
                     "padding embeds to zero); a coarse token is (S[b] - S[a]) / patch over its patch "
                     "steps, in float64 rounded to float32, a fine token one step's embedding",
        }
        doc["w_anomaly"] = float(detector.w_anomaly) if detector.supervised else 1.0
        doc["onset_level"] = detector._lower()
    if getattr(detector, "calibration_", None):
        doc["calibration"] = detector.calibration_
    doc["params"] = detector.saved_params()   # device: cpu, whatever it trained on
    doc["versions"] = package_versions((*PACKAGES, "onnx", "onnxruntime"))
    return doc


def __getattr__(name: str) -> Any:
    """``OnnxDetector`` and ``load_model``, which live in ``detectors.onnx_runtime``."""
    if name in ("OnnxDetector", "load_model"):
        from quadformer.detectors import onnx_runtime

        return getattr(onnx_runtime, name)
    raise AttributeError(f"module 'quadformer.detectors.export' has no attribute {name!r}")
