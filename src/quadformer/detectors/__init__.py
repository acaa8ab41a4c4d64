"""Attack detectors under one contract, registered by name."""

from quadformer.detectors import classical  # noqa: F401  (registers the classical methods)
from quadformer.detectors.base import Detector, NotFittedError, flight_slices
from quadformer.detectors.registry import available, get, load, make, register

__all__ = ["Detector", "NotFittedError", "available", "flight_slices", "get", "load", "make", "register"]
