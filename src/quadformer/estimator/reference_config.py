"""The GPS-free reference's tuning (``estimator.reference``), apart from its torch
filter: the detectors' attack typer reads its defaults without loading torch."""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["ReferenceConfig"]


@dataclass(frozen=True)
class ReferenceConfig:
    """How the GPS-free reference is compared with GPS (times in s, lengths in m)."""
    smooth_tau: float = 1.0          # s, smoothing of GPS minus reference
    vel_tau: float = 10.0            # s, averaging of the velocity difference (res_ref_vmean)
    horizons: tuple[float, float] = (5.0, 30.0)   # s, horizons of res_ref_h5 and res_ref_h30
    anchor_lag: float = 3.0          # s, how far behind the anchor follows while GPS agrees
    agree_window: float = 3.0        # s, GPS must agree this long before the anchor follows
    agree_k: float = 2.5             # both whitened horizontal position components of a - A below this: agreement
    release_k: float = 1.5           # after a disagreement, both below this, whitened as for a fresh anchor
    gps_slow_std: float = 0.5        # m, GPS position error correlated over tens of seconds
    gps_slow_tau: float = 30.0       # s, its correlation time
    pv_horizon: float = 5.0          # s, horizon of GPS velocity against the change of GPS position
    reset_std: float = 1.0           # m, horizontal position std above which the reference is reset

    def __post_init__(self) -> None:
        for name in ("smooth_tau", "vel_tau", "anchor_lag", "agree_window", "agree_k", "release_k",
                     "gps_slow_tau", "pv_horizon", "reset_std"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"reference.{name} must be a positive number, got {v!r}")
        if not (isinstance(self.gps_slow_std, (int, float)) and math.isfinite(self.gps_slow_std)
                and self.gps_slow_std >= 0):
            raise ValueError(f"reference.gps_slow_std must be a non-negative number, got {self.gps_slow_std!r}")
        h = tuple(self.horizons)
        if len(h) != 2 or not all(isinstance(v, (int, float)) and math.isfinite(v) and v > 0 for v in h):
            raise ValueError(f"reference.horizons must be two positive numbers of seconds, got {self.horizons!r}")
        if self.release_k > self.agree_k:
            raise ValueError(f"reference.release_k ({self.release_k}) must not exceed agree_k ({self.agree_k})")
        object.__setattr__(self, "horizons", tuple(float(v) for v in h))
