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

``OnnxDetector`` loads the files and honours the detector contract for scoring (offline
``decision_function``, ``stream``, the saved alarm rule); ``load_model(path, runtime)``
opens a saved model with PyTorch or onnxruntime.
"""

from __future__ import annotations

import hashlib
import json
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from quadformer.detectors.base import Detector, check_residues
from quadformer.detectors.context import Context
from quadformer.detectors.registry import load
from quadformer.detectors.windows import RawInputs, Windows, WindowStream
from quadformer.io import PACKAGES, atomic_path, package_versions, write_json

FORMAT = "quadformer-onnx"
FORMAT_VERSION = 2
READS = (1, 2)          # format versions this version loads (1: no streaming graph)
OPSET = 17
INPUT = "residues"
CONTEXT = "context"     # the streaming graph's second input
RUNTIMES = ("torch", "onnx")
#: windows per onnxruntime call offline: small batches keep the intermediate tensors in cache
#: (one thread, default sizes: QUADFormer scores about twice as many steps per second in
#: batches of 64 as in batches of 4096; CNN and LSTM gain 15 to 40%)
BATCH = 64


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
        spath = _stream_path(path)
        stream = {"graph": spath.name, "sha256": _export(step, example, spath, [INPUT, CONTEXT],
                                                         [*outputs, "embedding"], opset),
                  "width": int(step.steps.width)}
    write_json(_meta_path(path), _metadata(detector, digest, opset, stream))
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


def export_files(path: str | Path) -> list[Path]:
    """The files of the export at ``path`` (``NAME.onnx``) that exist: the graph, its metadata
    and, for QUADFormer, the streaming graph: what to copy together."""
    path = Path(path)
    return [p for p in (path, _meta_path(path), _stream_path(path)) if p.exists()]


def _meta_path(graph: Path) -> Path:
    return graph.with_name(graph.name + ".json")


def _stream_path(graph: Path) -> Path:
    """``model.onnx`` -> ``model.stream.onnx``."""
    return graph.with_name(graph.stem + ".stream.onnx")


def _pair(path: str | Path) -> tuple[Path, Path]:
    """(graph, metadata) from either file's path."""
    path = Path(path)
    if path.name.endswith(".onnx.json"):
        return path.with_name(path.name[: -len(".json")]), path
    if path.suffix == ".onnx":
        return path, _meta_path(path)
    raise ValueError(f"{path}: not an exported model (expected NAME.onnx or NAME.onnx.json)")


# -- the runtime ----------------------------------------------------------------------------
class OnnxDetector(Detector):
    """An exported network detector scored with onnxruntime, under the detector contract:
    ``features_``, ``threshold_``, ``budget_threshold_``, ``decision_function`` (the k-of-n
    rule for QUADFormer, outside the graph), ``predict``, ``stream``, and for QUADFormer
    ``predict_type`` and ``onset_times``. Scores equal the PyTorch detector's to float32
    rounding. It cannot be trained.

    ``path``: the ``.onnx`` graph or its ``.onnx.json``; ``threads``: onnxruntime intra-op
    threads (one by default: a flight computer shares its cores). The files are read and
    checked when the object is built.
    """

    name = "onnx"

    def __init__(self, path: str | Path, threads: int = 1) -> None:
        self.path = path
        self.threads = threads
        self._open()

    def _open(self) -> None:
        graph, meta = _pair(self.path)
        try:
            doc = json.loads(meta.read_text())
        except FileNotFoundError:
            raise FileNotFoundError(f"{meta}: no such file (the metadata written beside {graph.name})") from None
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise ValueError(f"{meta}: not an exported model's metadata (invalid JSON: {e})") from None
        if not isinstance(doc, dict) or doc.get("format") != FORMAT:
            raise ValueError(f"{meta}: not an exported model's metadata (format is not {FORMAT!r})")
        if doc.get("format_version") not in READS:
            raise ValueError(f"{meta}: format version {doc.get('format_version')!r} is not supported "
                             f"(this version reads {', '.join(map(str, READS))})")
        self._session = _session(_graph_bytes(graph, meta, doc.get("graph_sha256")), graph, self.threads)
        stream = doc.get("stream")
        self._stream = None
        if stream is not None:
            try:
                spath = graph.with_name(str(stream["graph"]))
                expected = stream["graph_sha256"]
                self.stream_width_ = int(stream["outputs"]["embedding"]["shape"][1])
            except (KeyError, TypeError, ValueError, IndexError) as e:
                raise ValueError(f"{meta}: incomplete metadata ({type(e).__name__}: {e})") from None
            self._stream = _session(_graph_bytes(spath, meta, expected), spath, self.threads)
        try:
            self.name = str(doc["method"])
            self.features_ = list(doc["features"])
            self.window = int(doc["window"])
            rule = doc["alarm_rule"]
            self.threshold_ = rule["threshold"]
            self.budget_threshold_ = rule["budget_threshold"]
            self.k = rule["k"]
            self.n = rule["n"]
            self.classes_ = doc["classes"]
            self.onset_level_ = doc.get("onset_level")
            self.inputs_ = RawInputs(np.asarray(doc["padding"], dtype=np.float32))
            c = doc.get("context") or {"window": self.window, "fine": self.window, "patch": 1}
            self.context = Context(int(c["window"]), int(c["fine"]), int(c["patch"]))
        except (KeyError, TypeError, ValueError) as e:
            raise ValueError(f"{meta}: incomplete metadata ({type(e).__name__}: {e})") from None
        if "calibration" in doc:
            self.calibration_ = doc["calibration"]
        self.metadata_ = doc
        outputs = ["score", "attack_class"] if self.classes_ else ["score"]
        inp = self._session.get_inputs()
        names = [o.name for o in self._session.get_outputs()]
        if (len(inp) != 1 or inp[0].name != INPUT or list(inp[0].shape[1:]) != [self.window, len(self.features_)]
                or not set(outputs) <= set(names) or len(self.inputs_.pad) != len(self.features_)):
            raise ValueError(f"{graph}: its inputs or outputs do not match {meta.name}")
        if self._stream is not None:
            inp = self._stream.get_inputs()
            names = [o.name for o in self._stream.get_outputs()]
            n_ctx = self.context.n_tokens - 1
            if ([i.name for i in inp] != [INPUT, CONTEXT] or list(inp[0].shape[1:]) != [len(self.features_)]
                    or list(inp[1].shape[1:]) != [n_ctx, self.stream_width_]
                    or not {*outputs, "embedding"} <= set(names)):
                raise ValueError(f"{graph.with_name(doc['stream']['graph'])}: its inputs or outputs do not match "
                                 f"{meta.name}")
        self._outputs = outputs
        self._names = np.array(self.classes_ or [], dtype=object)
        self.fitted_ = True

    # -- contract -------------------------------------------------------------------------
    def fit(self, X: pd.DataFrame, y: np.ndarray | None = None) -> "OnnxDetector":
        raise NotImplementedError(f"{self.name}: an exported ONNX model cannot be trained; fit the PyTorch "
                                  "detector and export it again")

    def save(self, path: str | Path) -> Path:
        raise NotImplementedError(f"{self.name}: an exported ONNX model is saved by export_onnx from the "
                                  "PyTorch detector")

    def score_windows(self, windows: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Scores (before any k-of-n rule) and attack types of RAW windows (n, W, features)."""
        out = self._session.run(self._outputs, {INPUT: np.ascontiguousarray(windows, dtype=np.float32)})
        return out[0], (self._names[out[1]] if self.classes_ else None)

    def raw_scores(self, X: pd.DataFrame) -> tuple[np.ndarray, np.ndarray | None]:
        """Per-step score of each causal window and, for QUADFormer, attack class index (before
        the k-of-n rule). The last result is cached by content, as ``QUADFormer.raw_scores``."""
        self.check_fitted()
        values = check_residues(X, self.features_)
        key = hashlib.blake2b(values.tobytes(), digest_size=16)
        key.update(pd.util.hash_pandas_object(X["flight_id"], index=False).to_numpy().tobytes())
        cache = self.__dict__.setdefault("_cache", {})
        if cache.get("key") != key.hexdigest():
            win = Windows(X, self.features_, self.inputs_, self.window)
            score = np.empty(len(win), dtype=np.float64)
            cls = np.empty(len(win), dtype=np.int64) if self.classes_ else None
            for i in range(0, len(win), BATCH):
                idx = np.arange(i, min(i + BATCH, len(win)))
                out = self._session.run(self._outputs, {INPUT: win[idx]})
                score[idx] = out[0]
                if cls is not None:
                    cls[idx] = out[1]
            cache.update(key=key.hexdigest(), score=score, cls=cls)
        return cache["score"], cache["cls"]

    def clear_cache(self) -> None:
        """Forget the cached scores (timings)."""
        self.__dict__.pop("_cache", None)

    def decision_function(self, X: pd.DataFrame) -> np.ndarray:
        from quadformer.detectors.neural.quadformer import kth_of_last_n

        raw, _ = self.raw_scores(X)
        return raw.copy() if self.k is None else kth_of_last_n(raw, X, self.k, self.n)

    @property
    def predict_type(self):
        """Predicted attack type at each step (QUADFormer only: absent for the others, as on the
        PyTorch detectors)."""
        if not self.classes_:
            raise AttributeError(f"{self.name}: does not classify attacks")
        return self._predict_type

    def _predict_type(self, X: pd.DataFrame) -> np.ndarray:
        _, cls = self.raw_scores(X)
        return self._names[cls]

    @property
    def onset_times(self):
        """(flight, alarm time, estimated onset time) per alarm run (QUADFormer only)."""
        if self.onset_level_ is None:
            raise AttributeError(f"{self.name}: has no onset criterion")
        return self._onset_times

    def _onset_times(self, X: pd.DataFrame, alarms: np.ndarray) -> list[tuple[Any, float, float]]:
        from quadformer.detectors.neural.quadformer import onset_times

        raw, _ = self.raw_scores(X)
        return onset_times(X, alarms, raw, self.onset_level_)

    def score_step(self, x: np.ndarray, context: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The streaming graph on one step of windows: raw residues x (n, features) and the
        token means of the embeddings of the windows' earlier steps (n, T-1, width) -> raw
        scores, attack type names and the steps' embeddings (QUADFormer exported in format 2)."""
        if self._stream is None:
            raise AttributeError(f"{self.name}: no streaming graph (exported in format version 1, or not QUADFormer)")
        out = self._stream.run([*self._outputs, "embedding"], {INPUT: np.ascontiguousarray(x, dtype=np.float32),
                                                                 CONTEXT: context})
        return out[0], self._names[out[1]], out[2]

    def stream(self, n_flights: int = 1) -> WindowStream:
        """Online scoring: the streaming graph one step at a time where there is one (``StepStream``),
        else the graph on each step's whole window (a ring buffer of the last window)."""
        if self.k is None:
            return WindowStream(self, n_flights, self.inputs_)
        from quadformer.detectors.neural.quadformer import KofNStream, StepStream

        if self._stream is not None:
            return StepStream(self, n_flights, self.score_step, self.inputs_, self.stream_width_)
        return KofNStream(self, n_flights, self.inputs_)


def _graph_bytes(graph: Path, meta: Path, sha256: str | None) -> bytes:
    """A graph's file, checked against the checksum its metadata gives."""
    try:
        data = graph.read_bytes()
    except FileNotFoundError:
        raise FileNotFoundError(f"{graph}: no such file (a graph of {meta.name})") from None
    if hashlib.sha256(data).hexdigest() != sha256:
        raise ValueError(f"{graph}: not the graph {meta.name} was written for (its checksum differs: "
                         "truncated, damaged or replaced); export it again")
    return data


def _session(data: bytes, graph: Path, threads: int):
    try:
        import onnxruntime as ort
    except ImportError:
        raise ImportError("onnxruntime is needed to score exported models: pip install onnxruntime") from None
    if not (isinstance(threads, (int, np.integer)) and threads >= 1):
        raise ValueError(f"threads must be an integer >= 1, got {threads!r}")
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = int(threads)
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    try:
        # onnxruntime's fusion of an Add and a LayerNormalization into SkipLayerNormalization
        # costs time on these small tensors (about 25 of 170 us of a streaming step; offline
        # windows score as fast either way)
        return ort.InferenceSession(data, opts, providers=["CPUExecutionProvider"],
                                    disabled_optimizers=["SkipLayerNormFusion"])
    except Exception as e:    # onnxruntime raises its own types (InvalidProtobuf, Fail, ...)
        msg = str(e).splitlines()[0] if str(e) else ""
        raise ValueError(f"{graph}: not a loadable ONNX graph ({type(e).__name__}: {msg})") from None


def load_model(path: str | Path, runtime: str = "torch", *, threads: int = 1) -> Detector:
    """A saved detector for scoring: ``runtime="torch"`` rebuilds it from its JSON
    (``detectors.load``); ``"onnx"`` opens an exported graph (``NAME.onnx`` or
    ``NAME.onnx.json``) with onnxruntime (``threads`` intra-op threads)."""
    if runtime not in RUNTIMES:
        raise ValueError(f"unknown runtime {runtime!r}; choose one of {', '.join(RUNTIMES)}")
    if runtime == "onnx":
        return OnnxDetector(path, threads=threads)
    if Path(path).suffix == ".onnx" or Path(path).name.endswith(".onnx.json"):
        raise ValueError(f"{path}: an exported ONNX model; load it with runtime='onnx'")
    return load(path)
