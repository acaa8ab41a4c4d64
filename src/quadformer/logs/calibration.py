"""Per-vehicle calibration: a fitted detector's alarm threshold set on one vehicle's own clean flights.

A detector trained in simulation meets a real vehicle's own noise; its threshold is set again
from that vehicle's clean logs at a false-alarm budget (at most ``per_hour`` alarm runs per
flight-hour, ``detectors.calibration.budget_threshold``), and what it was calibrated on is
recorded in the model (``calibration_``). How many false alarms it will see is estimated by
leaving one log out: each log scored at the threshold the other logs give, the alarm runs
summed over the logs with a Poisson 95% interval on the rate. Scores come from the logs'
residue rows (``logs.detect.log_rows``) as ``detect`` computes them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pandas as pd

from quadformer.estimator.filter_config import FilterConfig
from quadformer.logs import read_log
from quadformer.logs.detect import log_rows
from quadformer.logs.flightlog import LogError

__all__ = ["VehicleCalibration", "calibrate_on_logs", "poisson_interval"]

MIN_LOGS = 2          # leaving one out needs another to calibrate on


@dataclass
class VehicleCalibration:
    detector: Any                      # the detector, its threshold set (in place)
    per_hour: float                    # the budget: alarm runs per flight-hour on clean flights
    threshold: float
    hours: float                       # clean flight-hours calibrated on
    logs: list[dict[str, Any]]         # per log: path, hours, steps, held-out threshold and alarm runs
    skipped: list[str] = field(default_factory=list)   # logs not used, and why
    held_out_alarms: int = 0
    held_out_rate: float = float("nan")                # alarm runs per hour, leaving one log out
    held_out_interval: tuple[float, float] = (float("nan"), float("nan"))


def poisson_interval(count: int, hours: float, level: float = 0.95) -> tuple[float, float]:
    """Exact (Garwood) interval of a Poisson rate per hour from ``count`` events in ``hours``."""
    from scipy.stats import chi2

    a = (1.0 - level) / 2
    lo = 0.0 if count == 0 else chi2.ppf(a, 2 * count) / 2
    hi = chi2.ppf(1 - a, 2 * count + 2) / 2
    return float(lo / hours), float(hi / hours)


def _alarm_runs(scores: np.ndarray, flights: np.ndarray, threshold: float) -> int:
    """Alarm runs (``score > threshold``) counted within each flight."""
    from quadformer.detectors.alarms import runs

    return sum(len(runs(scores[flights == f] > threshold)) for f in np.unique(flights))


def calibrate_on_logs(detector, paths: list[str | Path], per_hour: float = 1.0, residues: str = "ekf",
                      config: FilterConfig = FilterConfig(), format: str | None = None,
                      progress: Callable[[str], None] | None = None) -> VehicleCalibration:
    """Set ``detector``'s alarm threshold from clean flight logs of one vehicle (see the module
    text). Logs that cannot be scored are skipped and listed; at least two must be scored."""
    from quadformer.detectors.calibration import budget_threshold, gps_rate

    if not (isinstance(per_hour, (int, float)) and np.isfinite(per_hour) and per_hour > 0):
        raise ValueError(f"per_hour must be a positive number of false alarms per flight-hour, got {per_hour!r}")
    detector.check_fitted()
    frames, used, skipped = [], [], []
    for k, p in enumerate(map(Path, paths)):
        try:
            flights, _ = log_rows(read_log(p, format=format), residues, config)
        except LogError as e:
            skipped.append(str(e))
            continue
        rows = pd.concat([f.rows for f in flights], ignore_index=True)
        rows["flight_id"] = k * 1000 + rows["flight_id"].astype(np.int64)      # one id per log and segment
        frames.append(rows)
        used.append(p)
        if progress is not None:
            progress(str(p))
    if len(used) < MIN_LOGS:
        raise LogError(f"calibration needs at least {MIN_LOGS} scored clean logs, got {len(used)}"
                       + (": " + "; ".join(skipped) if skipped else ""))
    X = pd.concat(frames, ignore_index=True)
    scores = np.asarray(detector.decision_function(X), dtype=float)
    fid = X["flight_id"].to_numpy()
    _, log_of = np.unique(fid // 1000, return_inverse=True)            # log index 0..len(used)-1 per row
    rate = gps_rate(X)
    steps = np.bincount(log_of, minlength=len(used))
    hours = steps / rate / 3600.0
    per_log = []
    for i, p in enumerate(used):
        mine = log_of == i
        others = ~mine
        thr = budget_threshold(scores[others], fid[others], np.unique(fid[others]), float(hours.sum() - hours[i]),
                               per_hour)
        alarms = _alarm_runs(scores[mine], fid[mine], thr)
        per_log.append({"log": str(p), "hours": float(hours[i]), "steps": int(steps[i]), "held_out_threshold": thr,
                        "held_out_alarm_runs": alarms})
    total = float(hours.sum())
    before = {"threshold": getattr(detector, "threshold_", None),
              "calibration": getattr(detector, "calibration_", None)}
    detector.calibrate(X, criterion="budget", budget_per_hour=per_hour, gps_rate_hz=rate, scores=scores,
                       vehicle_logs=[str(p) for p in used], vehicle_hours=total, residues=residues,
                       false_alarm_budget_per_hour=per_hour, before_vehicle=before)
    n_alarms = sum(d["held_out_alarm_runs"] for d in per_log)
    held_rate = n_alarms / total
    lo, hi = poisson_interval(n_alarms, total)
    detector.calibration_.update(held_out_alarms_per_hour=held_rate, held_out_interval=[lo, hi])
    return VehicleCalibration(detector, float(per_hour), float(detector.threshold_), total, per_log, skipped,
                              n_alarms, held_rate, (lo, hi))
