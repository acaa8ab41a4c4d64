"""quadformer: GPS spoofing detection and resilient state estimation for quadrotors.

Data flow: missions -> plant -> sensors -> attacks -> estimator -> residues -> detectors ->
resilience; sources of flights (simulation, logs) produce datasets; experiments and reports
on top. The names below are loaded on first use, so ``import quadformer.logs`` (say) does
not pull in the simulator.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "AttackConfig": "quadformer.config", "ConfigError": "quadformer.config", "SimConfig": "quadformer.config",
    "Dataset": "quadformer.dataset", "DatasetError": "quadformer.dataset", "load_dataset": "quadformer.dataset",
    "write_dataset": "quadformer.dataset", "simulate": "quadformer.simulation",
}
__all__ = sorted(_EXPORTS)
__version__ = "0.1.0"


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'quadformer' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(list(globals()) + __all__)
