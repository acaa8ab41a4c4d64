"""Geometry shared by the vehicle, the sensors and the estimator: SO(3) maps for unit
quaternions, plane angles and batched products whose per-flight result does not depend on
the batch (torch), and the frame conversions of the log readers (``frames``, numpy only).

The torch names below are loaded on first use, so ``from quadformer.geometry import frames``
(the log readers) does not load torch."""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {"atan2": "angles", "wrap_angle": "angles", "bmm": "linalg", "matvec": "linalg",
            "exp_quat": "so3", "exp_rotmat": "so3", "log_quat": "so3"}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"quadformer.geometry.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module 'quadformer.geometry' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(list(globals()) + __all__)
