"""The format of an exported detector (``detectors.export`` writes it, ``detectors.onnx_runtime``
scores it): its name and versions, the graphs' inputs, the runtimes, and which files belong
together."""

from __future__ import annotations

from pathlib import Path

__all__ = ["BATCH", "CONTEXT", "FORMAT", "FORMAT_VERSION", "INPUT", "OPSET", "READS", "RUNTIMES", "export_files",
           "graph_and_meta", "meta_path", "stream_path"]

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


def export_files(path: str | Path) -> list[Path]:
    """The files of the export at ``path`` (``NAME.onnx``) that exist: the graph, its metadata
    and, for QUADFormer, the streaming graph: what to copy together."""
    path = Path(path)
    return [p for p in (path, meta_path(path), stream_path(path)) if p.exists()]


def meta_path(graph: Path) -> Path:
    return graph.with_name(graph.name + ".json")


def stream_path(graph: Path) -> Path:
    """``model.onnx`` -> ``model.stream.onnx``."""
    return graph.with_name(graph.stem + ".stream.onnx")


def graph_and_meta(path: str | Path) -> tuple[Path, Path]:
    """(graph, metadata) from either file's path."""
    path = Path(path)
    if path.name.endswith(".onnx.json"):
        return path.with_name(path.name[: -len(".json")]), path
    if path.suffix == ".onnx":
        return path, meta_path(path)
    raise ValueError(f"{path}: not an exported model (expected NAME.onnx or NAME.onnx.json)")
