"""Resilient state estimation: per-flight GPS admission policies driven by a detector.

The names below are loaded on first use, so the online step (``resilience.step``) scores and
labels alerts without loading torch when no admission policy runs."""

from __future__ import annotations

import importlib
from typing import Any

__all__ = ["POLICIES", "READMIT_CLEAR", "READMIT_STALE", "Admission", "AdmissionConfig", "AdmissionGroup",
           "Decision"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        return getattr(importlib.import_module("quadformer.resilience.admission"), name)
    raise AttributeError(f"module 'quadformer.resilience' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(list(globals()) + __all__)
