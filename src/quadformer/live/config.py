"""What the live monitor is told and what it hands back: ``MonitorConfig`` (how it listens,
decides and acts), ``monitor_sensors`` (the sensors its filter fuses, checked against the
detector) and ``FixRecord`` (one scored GPS fix, for ``on_fix``)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from quadformer.config import SENSOR_NAMES
from quadformer.detectors.attack_types import TYPINGS
from quadformer.estimator.online import FilterConfig
from quadformer.estimator.schema import GROUPS, SENSOR_GROUPS
from quadformer.resilience.admission import AdmissionConfig

__all__ = ["FixRecord", "MonitorConfig", "monitor_sensors"]


@dataclass(frozen=True)
class MonitorConfig:
    """How the monitor listens, decides and acts. Times in seconds."""
    connect: str                                   # any pymavlink connection string
    filter: FilterConfig = field(default_factory=FilterConfig)
    admission: AdmissionConfig = field(default_factory=AdmissionConfig)
    gps_instance: int | None = None                # receiver: 0 GPS_RAW_INT, 1 GPS2_RAW; None: first with a 3D fix
    system: int | None = None                      # vehicle system id; None: the first that sends sensor data
    act: bool = False                              # switch the vehicle's EKF source set on exclusion/re-admission
    act_source_set: int = 2                        # the vehicle's non-GPS source set (1..3)
    statustext: bool = True                        # send STATUSTEXT alerts to the vehicle
    request_rates: bool = False                    # ask the vehicle for the streams it needs (SET_MESSAGE_INTERVAL)
    out: Path | None = None                        # directory for alerts.jsonl, fixes.csv, summary.json
    duration_s: float | None = None                # stop after this long (wall clock)
    max_messages: int | None = None                # stop after this many messages
    status_s: float = 1.0                          # status line period (wall clock)
    stale_s: float = 1.0                           # a stream silent this long is reported stopped
    restart_s: float = 1.0                         # clock going back this far is a restart
    restart_confirm: int = 3                       # samples in a row that confirm a restart
    recv_timeout_s: float = 0.1                    # longest wait for one message
    heartbeat_s: float = 1.0                       # own HEARTBEAT period (routers forward to known peers)
    source_system: int = 255                       # this monitor's MAVLink identity
    source_component: int = 191                    # MAV_COMP_ID_ONBOARD_COMPUTER
    typing: str = "shape"                          # alert types: attack_types.TYPINGS

    def __post_init__(self) -> None:
        if not isinstance(self.connect, str) or not self.connect:
            raise ValueError("monitor.connect: a pymavlink connection string, e.g. udpin:127.0.0.1:14550")
        if self.gps_instance not in (None, 0, 1):
            raise ValueError(f"monitor.gps_instance must be 0 (GPS_RAW_INT) or 1 (GPS2_RAW), got {self.gps_instance!r}")
        if self.act_source_set not in (1, 2, 3):
            raise ValueError(f"monitor.act_source_set must be 1, 2 or 3, got {self.act_source_set!r}")
        for name in ("status_s", "stale_s", "restart_s", "recv_timeout_s", "heartbeat_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"monitor.{name} must be a positive number of seconds, got {v!r}")
        if self.duration_s is not None and not self.duration_s > 0:
            raise ValueError(f"monitor.duration_s must be > 0, got {self.duration_s!r}")
        if self.max_messages is not None and not self.max_messages >= 1:
            raise ValueError(f"monitor.max_messages must be >= 1, got {self.max_messages!r}")
        if self.typing not in TYPINGS:
            raise ValueError(f"monitor.typing: unknown {self.typing!r}; choose from {', '.join(TYPINGS)}")
        if not (isinstance(self.restart_confirm, int) and self.restart_confirm >= 1):
            raise ValueError(f"monitor.restart_confirm must be an integer >= 1, got {self.restart_confirm!r}")

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["out"] = None if self.out is None else str(self.out)
        return d


@dataclass(frozen=True)
class FixRecord:
    """One scored GPS fix, handed to ``on_fix`` (the monitor keeps none)."""
    segment: int
    t: float                       # s since the link's first sensor sample (the monitor's time base)
    score: float
    alarm: bool
    attack_type: str | None
    admission: str                 # state after this fix's decision
    phase: str                     # the flight phase at the fix (detectors.flight_phase.PHASES)
    std_scale: float               # GPS noise factor the admission asks for (blend)
    nis: float
    gps_pos: np.ndarray            # ENU m about the origin
    est_pos: np.ndarray
    ap_pos: np.ndarray             # the autopilot's own estimate (NaN when not received)
    latency_s: float               # from the message in hand to the admission decision
    columns: dict[str, float]      # the residue row as scored


def monitor_sensors(detector, config: FilterConfig) -> str:
    """The sensors the monitor's filter fuses: ``config.sensors``, else those of the data the
    detector was fit on, else GPS, IMU and the aiding sensors whose residues it reads. Raises
    ValueError when the detector reads residues that configuration cannot produce."""
    sensors = config.sensors
    if sensors is None:
        sim = (getattr(detector, "calibration_", None) or {}).get("sim_config") or {}
        sensors = sim.get("sensors")
    if sensors is None:
        feats = set(detector.features_)
        need = {s for s, groups in SENSOR_GROUPS.items() if any(c in feats for g in groups for c in GROUPS[g].columns)}
        sensors = "+".join(s for s in SENSOR_NAMES if s in {"gps", "imu"} | need)
    parts = set(sensors.split("+"))
    if not {"gps", "imu"} <= parts or parts - set(SENSOR_NAMES):
        raise ValueError(f"sensors: {sensors!r} must join gps, imu and any of vio, mag, baro with '+'")
    sensors = "+".join(s for s in SENSOR_NAMES if s in parts)
    absent = {g for s, groups in SENSOR_GROUPS.items() if s not in parts for g in groups}
    have = {c for g in GROUPS.values() if g.name not in absent for c in g.columns}
    lacking = [c for c in detector.features_ if c not in have]
    if lacking:
        raise ValueError(f"detector {detector.name} reads {', '.join(lacking[:4])}, which a filter fusing {sensors} "
                         f"does not produce; choose --sensors with the sensors it was fit with")
    return sensors
