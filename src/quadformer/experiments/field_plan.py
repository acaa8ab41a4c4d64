"""What the field benchmark (``experiments.field``) runs on: its plan (``FieldPlan``: the methods,
the simulated training, the budget, the spoofs injected), the kinds of spoof it injects
(``INJECTED``) and a replayed log as it uses it (``FieldLog``: rows, flight phase, the manifest's
word, the vehicle). Shared by the benchmark, its detectors' origin (``field_models``) and its
injections (``field_spoofs``)."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from quadformer.config import SimConfig, merge
from quadformer.detectors.flight_phase import PhaseRule
from quadformer.logs.flightlog import FlightLog
from quadformer.logs.manifest import ManifestEntry

__all__ = ["INJECTED", "FieldLog", "FieldPlan", "Injection"]


@dataclass(frozen=True)
class Injection:
    """One kind of spoof the field benchmark injects."""
    kind: str                    # the attack kind (``config.ATTACK_KINDS``)
    seed_offset: int             # added to the injection's flight index (each kind its own draws)
    onset_step: bool | None = None   # a drift's onset style
    size: str = "rate"           # the AttackBatch field its size is (m or m/s)


#: the spoofs injected, by the name their results rows carry; bias and ramp keep the flight indices
#: (and so the draws) they had before the others existed, the others are offset far beyond them
INJECTED = {"bias": Injection("bias", 0, size="magnitude"), "ramp": Injection("ramp", 500),
            "drift": Injection("drift", 100_000_000, onset_step=True),
            "drift-accel": Injection("drift", 200_000_000, onset_step=False),
            "capture": Injection("capture", 300_000_000, size="magnitude")}


@dataclass(frozen=True)
class FieldPlan:
    methods: tuple[str, ...]
    flights: int = 60                     # simulated training flights
    duration: float = 60.0                # s per simulated flight
    model: str = "I"
    seed: int = 0
    budget_per_hour: float = 1.0          # false alarms per in-air hour, for the calibrated threshold
    label_fraction: float = 0.2
    injections: int = 6                   # spoofs of each kind injected into each clean segment in air
    bias: tuple[float, float] = (1.0, 10.0)       # m
    ramp: tuple[float, float] = (0.05, 2.0)       # m/s
    phase: PhaseRule = PhaseRule()
    drift: tuple[float, float] = (0.2, 2.0)       # m/s, a drift's rate (switched on at once or accelerating in)
    drift_accel: tuple[float, float] = (0.05, 0.5)  # m/s^2, an accelerating drift's acceleration
    capture: tuple[float, float] = (5.0, 15.0)    # m, a capture's pull-off
    capture_rate: tuple[float, float] = (0.5, 3.0)  # m/s, the drift after a capture
    kinds: tuple[str, ...] = tuple(INJECTED)      # the spoofs injected (names of field_spoofs.INJECTED)

    def __post_init__(self) -> None:
        unknown = [k for k in self.kinds if k not in INJECTED]
        if unknown:
            raise ValueError(f"FieldPlan.kinds: unknown injection {unknown[0]!r}; choose from {', '.join(INJECTED)}")

    def sim_config(self, noise_overrides: dict[str, Any]) -> SimConfig:
        return SimConfig.from_dict(merge(noise_overrides, {
            "model": self.model, "noise": "gaussian", "sensors": "gps+imu+mag+baro", "flights": self.flights,
            "duration": self.duration, "seed": self.seed,
            "attack": {"kind": "mix", "mix": ["bias", "ramp"], "magnitude": list(self.bias), "rate": list(self.ramp),
                       "onset": [self.duration / 6, self.duration * 2 / 3]}}))


@dataclass
class FieldLog:
    """One log as the benchmark uses it: its rows (``ekf`` residues), each row's flight phase."""
    path: Path
    log: FlightLog
    entry: ManifestEntry | None
    rows: pd.DataFrame
    phase: np.ndarray
    notes: list[str] = field(default_factory=list)

    @property
    def clean(self) -> bool:
        return self.entry is None or self.entry.clean

    @property
    def vehicle(self) -> str:
        """The vehicle the log was flown on: the manifest's ``vehicle`` without firmware hashes
        (one airframe across firmware builds), else the log's own name."""
        v = (self.entry.extra.get("vehicle") or "").strip() if self.entry is not None else ""
        return re.sub(r"\s*\([0-9a-f]{7,}\)", "", v).strip() or self.path.name

    @property
    def gps_t0(self) -> float:
        """The log's first GPS report (with or without a fix): the manifest's time origin."""
        first = [float(s["t"].iloc[0]) for s in (self.log.receiver, self.log.gps) if s is not None and len(s)]
        return min(first)

    def windows(self) -> list[tuple[float, float]]:
        """The manifest's GPS-trouble windows on the log's clock."""
        t0 = self.gps_t0
        return [] if self.entry is None else [(a + t0, b + t0) for a, b in self.entry.trouble]

    def signs(self) -> list[float]:
        """The manifest's first signs of GPS trouble on the log's clock."""
        t0 = self.gps_t0
        return [] if self.entry is None else [s + t0 for s in self.entry.signs]
