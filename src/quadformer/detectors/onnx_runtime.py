"""Exported network detectors scored with onnxruntime (the files ``detectors.export`` writes,
its docstring states them): ``OnnxDetector`` under the detector contract, and ``load_model``,
which opens a saved model with PyTorch or onnxruntime."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from quadformer.detectors.base import Detector, check_residues
from quadformer.detectors.context import Context
from quadformer.detectors.onnx_files import BATCH, CONTEXT, FORMAT, INPUT, READS, RUNTIMES, graph_and_meta
from quadformer.detectors.registry import load
from quadformer.detectors.windows import RawInputs, Windows, WindowStream

__all__ = ["OnnxDetector", "load_model"]


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
        graph, meta = graph_and_meta(self.path)
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
        from quadformer.detectors.neural.quadformer_alarms import kth_of_last_n

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
        from quadformer.detectors.neural.quadformer_alarms import onset_times

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
        from quadformer.detectors.neural.quadformer_alarms import KofNStream, StepStream

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
