"""Sensors: IMU (100 Hz), GPS (10 Hz), stereo VIO (20 Hz), magnetometer (50 Hz) and
barometer (25 Hz), with shaped noise.

The names below are loaded on first use, so ``from quadformer.sensors.mavlink import ...``
(the telemetry log reader) does not load the batched models' torch."""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {"GPS": "_models", "IMU": "_models", "VIO": "_models", "Barometer": "_models", "ChunkedNoise": "_models",
            "Magnetometer": "_models", "batch_noise": "noise", "standard_noise": "noise"}
__all__ = ["GPS", "IMU", "VIO", "Barometer", "ChunkedNoise", "Magnetometer", "batch_noise",
           "standard_noise"]


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"quadformer.sensors.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module 'quadformer.sensors' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(list(globals()) + __all__)
