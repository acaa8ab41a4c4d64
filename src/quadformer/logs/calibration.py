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
from quadformer.logs.vehicle import vehicle_identity

__all__ = ["VehicleCalibration", "VehicleProfile", "calibrate_on_logs", "poisson_interval", "vehicle_profile"]

MIN_LOGS = 2          # leaving one out needs another to calibrate on
#: a vehicle profile narrows the shipped threshold only on at least this many budget periods of
#: clean flight in the air (at 1 false alarm per hour: 3 hours), so that the budget can be seen
BUDGET_PERIODS = 3.0
#: minutes of clean flight in the air a profile needs to set the vehicle's own noise scales
MIN_SCALE_MINUTES = 3.0
#: a threshold widened to the clean flights' largest score is kept this much above it
WIDEN_MARGIN = 1.1


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


@dataclass
class _Read:
    path: Path
    log: Any                      # the FlightLog
    rows: pd.DataFrame            # its segments' rows, flight ids ``1000 k + segment`` (k: the path's index)
    sensors: str
    delays: list[float] = field(default_factory=list)   # s, the receiver latencies estimated from its segments


def _check_budget(per_hour: float) -> None:
    if not (isinstance(per_hour, (int, float)) and np.isfinite(per_hour) and per_hour > 0):
        raise ValueError(f"per_hour must be a positive number of false alarms per flight-hour, got {per_hour!r}")


def _clean_rows(paths: list[str | Path], residues: str, config: FilterConfig, format: str | None,
                progress: Callable[[str], None] | None) -> tuple[list[_Read], list[str]]:
    """The rows of the clean logs that can be scored (one flight id per log and segment), and why
    the others could not."""
    read, skipped = [], []
    for k, p in enumerate(map(Path, paths)):
        try:
            log = read_log(p, format=format)
            flights, _ = log_rows(log, residues, config)
        except LogError as e:
            skipped.append(str(e))
            continue
        rows = pd.concat([f.rows for f in flights], ignore_index=True)
        rows["flight_id"] = k * 1000 + rows["flight_id"].astype(np.int64)
        read.append(_Read(p, log, rows, flights[0].sensors,
                          [f.gps_delay_s for f in flights if getattr(f, "delay_estimated", False)]))
        if progress is not None:
            progress(str(p))
    return read, skipped


def calibrate_on_logs(detector, paths: list[str | Path], per_hour: float = 1.0, residues: str = "ekf",
                      config: FilterConfig = FilterConfig(), format: str | None = None,
                      progress: Callable[[str], None] | None = None) -> VehicleCalibration:
    """Set ``detector``'s alarm threshold from clean flight logs of one vehicle (see the module
    text). Logs that cannot be scored are skipped and listed; at least two must be scored."""
    from quadformer.detectors.calibration import budget_threshold, gps_rate

    _check_budget(per_hour)
    detector.check_fitted()
    read, skipped = _clean_rows(paths, residues, config, format, progress)
    used = [r.path for r in read]
    if len(used) < MIN_LOGS:
        raise LogError(f"calibration needs at least {MIN_LOGS} scored clean logs, got {len(used)}"
                       + (": " + "; ".join(skipped) if skipped else ""))
    X = pd.concat([r.rows for r in read], ignore_index=True)
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


# --------------------------------------------------------------------------- vehicle profiles
@dataclass
class VehicleProfile:
    detector: Any                      # glr with the vehicle's scales and threshold (in place)
    identity: dict[str, Any]
    sensors: str
    minutes: float                     # clean minutes in the air the profile rests on
    needed_minutes: float              # what narrowing the threshold at the budget needs
    narrowed: bool                     # whether the threshold was set from these flights at the budget
    threshold: float
    shipped_threshold: float
    scales_set: bool                   # whether the vehicle's own noise scales replaced the trained ones
    logs: list[str]
    skipped: list[str] = field(default_factory=list)
    message: str = ""


def vehicle_profile(detector, paths: list[str | Path], per_hour: float = 1.0, config: FilterConfig = FilterConfig(),
                    format: str | None = None, progress: Callable[[str], None] | None = None) -> VehicleProfile:
    """A vehicle profile for ``glr``: its noise scales from the vehicle's clean flights in the air
    (at least ``MIN_SCALE_MINUTES``), used from take-off; its threshold set at ``per_hour`` from these
    flights only when they hold ``BUDGET_PERIODS`` budget periods in the air, else never below the
    shipped one (widened to ``WIDEN_MARGIN`` times the flights' largest score where that is higher);
    the vehicle (``vehicle_identity``) and the sensors fused recorded, so that ``check_profile``
    refuses another's logs. The logs must be of one vehicle."""
    from quadformer.detectors.calibration import budget_threshold, gps_rate
    from quadformer.detectors.flight_scales import robust_scale
    from quadformer.detectors.glr import INPUTS, step_features

    if getattr(detector, "name", None) != "glr":
        raise ValueError(f"a vehicle profile normalises glr (its noise scales and threshold); {detector.name} is "
                         "calibrated on a vehicle's flights with calibrate_on_logs (quadformer calibrate without "
                         "--profile)")
    _check_budget(per_hour)
    detector.check_fitted()
    read, skipped = _clean_rows(paths, "ekf", config, format, progress)
    used = [r.path for r in read]
    ids = [vehicle_identity(r.log) for r in read]
    sensors = {r.sensors for r in read}
    if not used:
        raise LogError("a vehicle profile needs clean logs that can be scored" + (": " + "; ".join(skipped)
                                                                                   if skipped else ""))
    boards = {i["board"] for i in ids if i["board"]}
    if len(boards) > 1 or len({i["autopilot"] for i in ids}) > 1:
        raise LogError("the clean logs are of more than one vehicle (boards " + ", ".join(sorted(boards)) + "): a "
                       "profile is one vehicle's")
    if len(sensors) > 1:
        raise LogError(f"the clean logs fuse different sensors ({', '.join(sorted(sensors))}); give logs of one sensor "
                       "set, or --sensors")
    X = pd.concat([r.rows for r in read], ignore_index=True)
    air = X["in_air"].to_numpy(dtype=float) > 0.5 if "in_air" in X.columns else np.ones(len(X), bool)
    rate = gps_rate(X)
    minutes = float(air.sum()) / rate / 60.0
    needed = BUDGET_PERIODS / per_hour * 60.0
    shipped = float(detector.threshold_)
    scales_set = minutes >= MIN_SCALE_MINUTES
    if scales_set:
        d = []
        for fid, g in X.groupby("flight_id", sort=False):
            feats = step_features(g["t"].to_numpy(dtype=float), g[list(INPUTS)].to_numpy(dtype=float),
                                  detector.windows, detector.reference_s)
            d.append(feats[air[g.index.to_numpy()]])
        own = robust_scale(np.vstack(d), detector.quantile)
        detector.scale_ = np.where(np.isfinite(own), np.maximum(own, 1e-6), detector.scale_)
        detector.vehicle_ = True
    scores = np.asarray(detector.decision_function(X), dtype=float)
    fid = X["flight_id"].to_numpy()
    narrowed = minutes >= needed
    if narrowed:
        thr = budget_threshold(scores[air], fid[air], np.unique(fid[air]), minutes / 60.0, per_hour)
        message = (f"threshold set from {minutes:.1f} clean minutes in the air at {per_hour:g} false alarm(s) per "
                   "hour")
    else:
        top = float(scores[air].max()) if air.any() else 0.0
        thr = max(shipped, WIDEN_MARGIN * top)
        message = (f"threshold not narrowed: {minutes:.1f} clean minutes in the air, and a budget of {per_hour:g} "
                   f"per hour needs {needed:.0f}; " + ("kept the shipped threshold" if thr == shipped else
                                                       f"widened above these flights' largest score ({top:.1f})"))
    if not scales_set:
        message += (f"; noise scales not set: {minutes:.1f} clean minutes in the air, at least {MIN_SCALE_MINUTES:g} "
                    "needed")
    identity = next((i for i in ids if i["board"]), ids[0])
    # the receiver's latency, where the logs had to be asked for it: the median of their estimates,
    # which a live link (that carries no setting) then uses
    delays = [d for r in read for d in r.delays]
    latency = float(np.median(delays)) if delays else None
    if latency is not None:
        message += f"; receiver latency {latency * 1e3:.0f} ms (the median estimate of {len(delays)} segment(s))"
    detector.calibrate(thr, thr, vehicle=identity, vehicle_sensors=sensors.pop(), vehicle_minutes=minutes,
                       vehicle_gps_delay_s=latency,
                       vehicle_needed_minutes=needed, vehicle_narrowed=narrowed, vehicle_scales_set=scales_set,
                       vehicle_logs=[str(p) for p in used], false_alarm_budget_per_hour=per_hour,
                       shipped_threshold=shipped, **{k: v for k, v in (getattr(detector, "calibration_", None)
                                                                        or {}).items() if k == "sim_config"})
    cal = detector.calibration_
    return VehicleProfile(detector, identity, cal["vehicle_sensors"], minutes, needed, narrowed, thr, shipped,
                          scales_set, [str(p) for p in used], skipped, message)
