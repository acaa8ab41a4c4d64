"""Resilient state estimation: per-flight GPS admission policies driven by a detector."""

from quadformer.resilience.admission import (POLICIES, READMIT_CLEAR, READMIT_STALE, Admission, AdmissionConfig,
                                             AdmissionGroup, Decision)

__all__ = ["POLICIES", "READMIT_CLEAR", "READMIT_STALE", "Admission", "AdmissionConfig", "AdmissionGroup",
           "Decision"]
