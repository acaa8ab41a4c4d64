"""Attack detectors under one contract, registered by name."""

from quadformer.detectors import classical, svm  # noqa: F401  (registration)
from quadformer.detectors import neural  # noqa: F401  (registration)
from quadformer.detectors.base import Detector, NotFittedError, flight_slices
from quadformer.detectors.registry import available, defaults, get, load, make, register

__all__ = ["Detector", "NotFittedError", "available", "defaults", "flight_slices", "get", "load", "make", "register"]
