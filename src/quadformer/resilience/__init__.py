"""Resilient state estimation: alerts, GPS admission policies, and the closed-loop benchmark."""

from quadformer.resilience.admission import POLICIES, Admission, AdmissionConfig
from quadformer.resilience.alerts import Alert, alerts_frame, alerts_from_scores, write_alerts
from quadformer.resilience.online import OnlineScorer

__all__ = ["POLICIES", "Admission", "AdmissionConfig", "Alert", "OnlineScorer", "alerts_frame",
           "alerts_from_scores", "write_alerts"]
