"""quadformer: GPS spoofing detection and resilient state estimation for quadrotors.

Data flow: missions -> plant -> sensors -> attacks -> estimator -> residues -> detectors ->
resilience; sources of flights (simulation, logs) produce datasets; experiments and reports
on top. The names below are loaded on first use (PEP 562), so ``import quadformer`` is quick
and ``import quadformer.logs`` (say) does not pull in the simulator or torch.

    import quadformer
    result = quadformer.detect_log("flight.ulg")               # the shipped detector that fits the log
    detector = quadformer.pretrained("gps+imu+mag+baro")       # a shipped detector, calibrated
    detector = quadformer.make("cusum").fit(train).calibrate(val)   # or one of your own
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "AttackConfig": "quadformer.config", "ConfigError": "quadformer.config", "SimConfig": "quadformer.config",
    "Dataset": "quadformer.dataset", "DatasetError": "quadformer.dataset", "load_dataset": "quadformer.dataset",
    "write_dataset": "quadformer.dataset", "simulate": "quadformer.simulation",
    "make": "quadformer.detectors", "load": "quadformer.detectors",
    "split_flights": "quadformer.evaluation.protocol",
    "read_log": "quadformer.logs", "detect_log": "quadformer.logs.detect",
    "Monitor": "quadformer.live.monitor",
    "pretrained": ("quadformer.detectors.pretrained", "load"),
}
__all__ = sorted(_EXPORTS)
__version__ = "0.1.0"


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        module, attr = _EXPORTS[name] if isinstance(_EXPORTS[name], tuple) else (_EXPORTS[name], name)
        value = getattr(importlib.import_module(module), attr)
        globals()[name] = value      # later look-ups skip this function
        return value
    raise AttributeError(f"module 'quadformer' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
