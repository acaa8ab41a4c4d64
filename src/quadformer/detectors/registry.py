"""Detectors registered by name, so ``--methods`` can pick them and users can add theirs.

    from quadformer.detectors import register, Detector

    @register("mine")
    class Mine(Detector): ...
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

from quadformer.detectors.base import Detector

_REGISTRY: dict[str, type[Detector]] = {}
_EXTRA: set[str] = set()


def register(name: str, default: bool = True) -> Callable[[type[Detector]], type[Detector]]:
    """Register a detector; ``default=False`` (ablations) keeps it out of the default
    method list, though ``--methods NAME`` or ``--methods all`` still run it."""
    def deco(cls: type[Detector]) -> type[Detector]:
        if name in _REGISTRY and _REGISTRY[name] is not cls:
            raise ValueError(f"a detector named {name!r} is already registered")
        cls.name = name
        _REGISTRY[name] = cls
        if not default:
            _EXTRA.add(name)
        return cls
    return deco


def available() -> list[str]:
    """Every registered detector."""
    return list(_REGISTRY)


def defaults() -> list[str]:
    """The detectors a benchmark runs when no method is named."""
    return [n for n in _REGISTRY if n not in _EXTRA]


def get(name: str) -> type[Detector]:
    try:
        return _REGISTRY[name]
    except KeyError:
        raise KeyError(f"unknown detector {name!r}; available: {', '.join(_REGISTRY)}") from None


def make(name: str, **params) -> Detector:
    return get(name)(**params)


def load(path: str | Path) -> Detector:
    """Rebuild a detector saved by ``Detector.save``."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such model file") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: not a saved detector (invalid JSON: {e})") from None
    if not isinstance(doc, dict) or "method" not in doc:
        raise ValueError(f"{path}: not a saved detector (no 'method')")
    try:
        det = make(doc["method"], **doc.get("params", {}))
    except TypeError as e:
        raise ValueError(f"{path}: parameters do not fit detector {doc['method']!r} ({e})") from None
    det.load_state(doc.get("state", {}))
    det.load_extra(path)
    return det
