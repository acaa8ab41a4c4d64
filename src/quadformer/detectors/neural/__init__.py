"""Neural detectors: modules, the shared training loop, and their detector classes."""

from quadformer.detectors.neural.detector import CNNDetector, LSTMDetector, WindowClassifier
from quadformer.detectors.neural.quadformer import QUADFormer
from quadformer.detectors.neural.training import DEVICES, TrainConfig, resolve_device, train

__all__ = ["DEVICES", "CNNDetector", "LSTMDetector", "QUADFormer", "TrainConfig", "WindowClassifier", "resolve_device",
           "train"]
