"""Resilient state estimation: per-flight GPS admission policies driven by a detector."""

from quadformer.resilience.admission import POLICIES, Admission, AdmissionConfig, Decision

__all__ = ["POLICIES", "Admission", "AdmissionConfig", "Decision"]
