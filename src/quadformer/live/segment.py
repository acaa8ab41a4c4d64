"""One segment of the live monitor: a continuous stretch of the vehicle's clock. It holds the
residue stream (``estimator.online.ResidueStream``), fed one sample at a time, and the online
step that scores its rows (``resilience.step.OnlineStep``: detector stream, admission, alert
lifecycle and typer; the link's flight phase and the segment's own receiver health label its
alerts, as ``detect`` gives each segment of a log its own). A restart of the vehicle's clock,
an IMU gap longer than the filter's ``max_gap_s`` or an error ends a segment and starts the
next; GPS stays excluded across it until re-admitted by the rule."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from quadformer.detectors.attack_types import OnlineTyper, ShapeTyper
from quadformer.detectors.flight_phase import FlightPhase
from quadformer.detectors.receiver_health import ReceiverHealth
from quadformer.estimator.online import FilterConfig, ResidueStream
from quadformer.live.alerts import MAX_ALERTS
from quadformer.resilience.admission import EXCLUDED, Admission, AdmissionConfig
from quadformer.resilience.step import OnlineStep

__all__ = ["Segment"]


class Segment:
    """Segment ``index``, started for ``reason``; ``excluded``: the vehicle is still off GPS, so
    the admission starts excluded and re-admission follows the rule; ``phase``: the link's
    flight phase (None: alerts are not labelled by phase or receiver health)."""

    def __init__(self, index: int, reason: str, detector, filter_config: FilterConfig, sensors: str,
                 admission: AdmissionConfig, typer: ShapeTyper | None = None, excluded: bool = False,
                 phase: FlightPhase | None = None, resume: "Segment | None" = None):
        self.index, self.reason = index, reason
        self.max_gap_s = filter_config.max_gap_s
        self.stream = ResidueStream(filter_config, sensors, n=1)
        rule = Admission(["resilient"], filter_config.gps_rate_hz, admission)
        if excluded:
            rule.state[:] = EXCLUDED
        typer = None if typer is None else OnlineTyper(typer, filter_config.gps_rate_hz)
        health = None if phase is None else ReceiverHealth(flight_id=index, keep=MAX_ALERTS)
        self.step = OnlineStep(detector.stream(1), rule, flight_ids=[index], typer=typer, keep=MAX_ALERTS,
                               phase=phase, health=health)
        if resume is not None and hasattr(self.step.stream, "resume"):
            self.step.stream.resume(resume.step.stream)      # the detector's calibration goes on
        self.first_imu: float | None = None
        self.last_imu: float | None = None
        self.fixes = 0
        self.last_score = math.nan

    @property
    def state(self) -> int:
        """The admission state (``resilience.admission``: FUSING, EXCLUDED, BLENDING)."""
        return int(self.step.admission.state[0])

    def imu(self, t: float, x: np.ndarray) -> list[dict[str, Any]]:
        """Feed one IMU sample; the residue rows it completes. Raises ``GapError`` after a gap
        longer than ``max_gap_s`` (the segment ends there)."""
        if self.first_imu is None:
            self.first_imu = t
        rows = self.stream.imu(t, x)
        self.last_imu = t
        return rows

    def fusable(self, stream: str, t: float) -> bool:
        """Whether a GPS or aiding sample at ``t`` can be fused: not more than ``max_gap_s``
        after the last IMU sample (else it could never be, and would only queue)."""
        return not ((stream == "gps" or self.stream.filter is not None)
                    and (self.last_imu is None or t - self.last_imu > self.max_gap_s))

    def feed(self, stream: str, t: float, s, pos: np.ndarray | None = None) -> None:
        """Feed one attitude, GPS (``pos``: its ENU position), magnetometer, barometer or
        odometry sample."""
        if stream == "attitude":
            self.stream.attitude(t, s.q)
        elif stream == "gps":
            self.stream.gps(t, pos, s.vel, s.eph, s.epv, s.speed_acc)
        elif stream == "mag":
            self.stream.mag(t, s.field)
        elif stream == "baro":
            self.stream.baro(t, s.alt)
        else:
            self.stream.vio(t, np.concatenate([s.vel, s.q]))

    def score(self, t: float, row: dict[str, Any]):
        """Score one residue row and decide admission (``OnlineStep.update``); raises
        ValueError for non-finite residues (not scored)."""
        out = self.step.update(t, row)
        self.fixes += 1
        self.last_score = float(out.score[0])
        return out

    def describe(self, ended: str) -> dict[str, Any]:
        """The segment as the summary lists it."""
        return {"segment": self.index, "started": self.reason, "ended": ended, "fixes": self.fixes,
                "first_imu_t": self.first_imu, "last_imu_t": self.last_imu}
