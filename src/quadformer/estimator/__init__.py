"""Error-state EKF fusing IMU, GPS and, as configured, VIO, magnetometer and barometer; its
innovations are the residues.

The filter's names below are loaded on first use, so the residue schema
(``quadformer.estimator.schema``) and the reference's tuning
(``quadformer.estimator.reference_config``) are importable without torch."""

from __future__ import annotations

import importlib
from typing import Any

__all__ = ["ERROR_STATES", "EKFState", "Innovation", "NoiseModel", "baro_update", "gps_update", "init_state",
           "mag_update", "predict", "update", "vio_update"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        return getattr(importlib.import_module("quadformer.estimator.eskf"), name)
    raise AttributeError(f"module 'quadformer.estimator' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(list(globals()) + __all__)
