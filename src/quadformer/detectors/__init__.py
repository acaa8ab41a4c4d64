"""Attack detectors under one contract, registered by name: classical statistics, learned
window classifiers and QUADFormer; their online streams and alert events, labelled by flight
phase and receiver health; the network detectors exported as ONNX graphs and scored with
onnxruntime.

A detector's module is imported when the detector is first asked for by name (``get``,
``make``, ``load``; ``registry.BUILTIN``), so the classical ones score without loading torch."""

from quadformer.detectors.alarms import Alert, alert_counts, alerts_frame, alerts_from_scores, runs, write_alerts
from quadformer.detectors.attack_types import ShapeTyper
from quadformer.detectors.base import Detector, NotFittedError, flight_slices
from quadformer.detectors.export import export_onnx
from quadformer.detectors.flight_phase import FlightPhase, PhaseRule
from quadformer.detectors.impact import ImpactDetector, ImpactRule, impacts
from quadformer.detectors.onnx_runtime import OnnxDetector, load_model
from quadformer.detectors.receiver_health import HealthRule, ReceiverHealth
from quadformer.detectors.registry import available, defaults, get, load, make, register
from quadformer.detectors.streams import DetectorStream, StreamGroup, StreamStep

__all__ = ["Alert", "Detector", "DetectorStream", "FlightPhase", "HealthRule", "ImpactDetector", "ImpactRule",
           "NotFittedError", "OnnxDetector", "PhaseRule", "ReceiverHealth", "StreamGroup", "StreamStep", "alert_counts",
           "alerts_frame", "alerts_from_scores", "available", "defaults", "export_onnx", "flight_slices", "get",
           "impacts", "load", "load_model", "make", "register", "runs", "write_alerts"]
