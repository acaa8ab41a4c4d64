"""Detectors registered by name, so ``--methods`` can pick them and users can add theirs.

    from quadformer.detectors import register, Detector

    @register("mine")
    class Mine(Detector): ...

The built-in detectors are named in ``BUILTIN`` with their module, which is imported when one
of its detectors is first asked for (``get``, ``make``, ``load``): ``available()`` and
``defaults()`` list them without importing anything, and a classical detector never loads
torch.
"""

from __future__ import annotations

import importlib
import json
from pathlib import Path
from typing import Callable

from quadformer.detectors.base import Detector

_CLASSICAL = "quadformer.detectors.classical"
_QUADFORMER = "quadformer.detectors.neural.quadformer"
#: the built-in detectors, in the order of ``available()``: name -> (module that registers it,
#: whether a benchmark runs it by default)
BUILTIN: dict[str, tuple[str, bool]] = {
    "chi2": (_CLASSICAL, True), "cusum": (_CLASSICAL, True), "sprt": (_CLASSICAL, True), "bht": (_CLASSICAL, True),
    "chi2-vref": (_CLASSICAL, True), "cusum-vref": (_CLASSICAL, True), "cusum-ref": (_CLASSICAL, True),
    "pca": ("quadformer.detectors.pca", True), "svm": ("quadformer.detectors.svm", True),
    "cnn": ("quadformer.detectors.neural.detector", True), "lstm": ("quadformer.detectors.neural.detector", True),
    "quadformer": (_QUADFORMER, True), "quadformer-noprior": (_QUADFORMER, False),
    "quadformer-nosup": (_QUADFORMER, False), "quadformer-nodisc": (_QUADFORMER, False),
    "glr": ("quadformer.detectors.glr", False),
}
_REGISTRY: dict[str, type[Detector]] = {}
_EXTRA: set[str] = {name for name, (_, default) in BUILTIN.items() if not default}


def register(name: str, default: bool = True) -> Callable[[type[Detector]], type[Detector]]:
    """Register a detector; ``default=False`` (ablations) keeps it out of the default
    method list, though ``--methods NAME`` or ``--methods all`` still run it."""
    def deco(cls: type[Detector]) -> type[Detector]:
        taken = name in BUILTIN and cls.__module__ != BUILTIN[name][0]    # a built-in, loaded or not
        if taken or (name in _REGISTRY and _REGISTRY[name] is not cls):
            raise ValueError(f"a detector named {name!r} is already registered")
        cls.name = name
        _REGISTRY[name] = cls
        if not default:
            _EXTRA.add(name)
        return cls
    return deco


def available() -> list[str]:
    """Every registered detector: the built-in ones, then those registered since."""
    return [*BUILTIN, *(n for n in _REGISTRY if n not in BUILTIN)]


def defaults() -> list[str]:
    """The detectors a benchmark runs when no method is named."""
    return [n for n in available() if n not in _EXTRA]


def get(name: str) -> type[Detector]:
    """The detector class registered as ``name``, importing its module on first use."""
    if name not in _REGISTRY and name in BUILTIN:
        importlib.import_module(BUILTIN[name][0])
    try:
        return _REGISTRY[name]
    except KeyError:
        raise KeyError(f"unknown detector {name!r}; available: {', '.join(available())}") from None


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
