"""Reports: the detection benchmark's tables in the paper's layout, figures and an offline
HTML report; the resilience benchmark's policy tables and trajectory figures.

The names below are loaded on first use (PEP 562), so the report of a flight log
(``quadformer.report.logs``, ``detection_outputs``) does not pull in the benchmark's metrics."""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {"dataset_table": "quadformer.report.detection_tables", "overall_table": "quadformer.report.resilience",
            "paper_tables": "quadformer.report.detection_tables", "write_report": "quadformer.report.detection",
            "write_resilience_report": "quadformer.report.resilience"}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value      # later look-ups skip this function
        return value
    raise AttributeError(f"module 'quadformer.report' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
