"""The field benchmark: detectors trained in simulation, judged on real flight logs.

An autopilot engineer judges a spoofing detector on their own flights by how often it cries wolf
on a clean flight, what it says when the receiver loses its fix, and how soon it sees a spoof.
For each method (the benchmark's defaults), on the logs given:

1. Every log is read, or refused with its reason (``read``/``refused`` in the results).
2. The fleet's sensor noise is estimated from the clean logs (``logs.noise``) and each method is
   tuned on a simulated dataset of the logs' sensor configuration (GPS, IMU, magnetometer,
   barometer) with that noise, under the detection benchmark's protocol (split by flight,
   threshold on validation flights). No real log is used for training.
3. The logs are replayed through the project's filter with the simulation's tuning (``ekf``
   residues), scored, and their alerts raised through the online step with the log's own flight
   phase (arming, take-off and landing events, else height) and receiver health (fix type,
   accuracy, the autopilot's GPS glitch and failsafe events): each alert is ``spoofing`` or
   ``degraded``, raised on the ``ground``, in ``transition`` or in ``air``.
4. Two thresholds per method: the simulation's (``sim``; a shipped detector's own), and one
   calibrated on the fleet's own clean logs at ``budget_per_hour`` false alarms per in-air hour,
   leaving the scored log's vehicle out of its calibration (``calibrated``: every log of the same
   vehicle, the manifest's ``vehicle`` with firmware hashes removed, is left out; a log without
   one is a vehicle of its own). A false alarm is what step 5 counts, a spoofing alert in the air:
   an alarm that the receiver's trouble, a landing or the ground explains is not one.
5. Clean logs (per the manifest): spoofing alerts in air per in-air flight-hour with the exposure
   and a Poisson 95% interval; ground and transition alerts, and degraded alerts, apart.
6. Logs with GPS trouble (manifest windows): alerts inside the windows by kind, spoofing alerts
   outside them, and whether the receiver health raised a ``degraded`` alert within
   ``DEGRADED_WITHIN_S`` of each first sign.
7. Spoofs injected into the clean logs in air (bias, ramp, a drift switched on at once, an
   accelerating drift and an SDR capture, whose receiver reports are spoofed too; onset after
   take-off has settled, position and the matching velocity): event recall (a spoofing alert
   raised in air between the onset and the end of the injection), median and p95 delay, offset at
   detection, and recall on the offsets of at least 2 m and drifts of at least 0.2 m/s.
8. The physical floor of each clean log (``logs.noise.detection_floor``): the smallest offset and
   drift a test of one GPS interval tells from that log's own noise at the budget; recall is also
   given on the spoofs at or above both the targets' sizes and the log's floor (``recall_floor``).
"""

from __future__ import annotations

import copy
import dataclasses
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pandas as pd

from quadformer.config import SimConfig
from quadformer.detectors.calibration import budget_threshold
from quadformer.detectors.flight_phase import PhaseRule, phases
from quadformer.estimator.filter_config import FilterConfig
from quadformer.experiments.field_models import shipped_detectors, shipped_files, tune_methods
from quadformer.experiments.field_plan import FieldLog, FieldPlan
from quadformer.experiments.field_spoofs import inject, injected_events, log_alerts, planned_injections
from quadformer.experiments.provenance import provenance
from quadformer.io import package_versions, write_json
from quadformer.logs import LogError, read_log
from quadformer.logs.detect import log_height, log_impacts, log_rows
from quadformer.logs.flightlog import FlightLog
from quadformer.logs.manifest import ManifestEntry, read_manifest
from quadformer.logs.replay import ekf_flights, missing_features

__all__ = ["FieldPlan", "run_field"]

DEGRADED_WITHIN_S = 2.0     # s after a receiver's first sign of trouble, the degraded alert's deadline


def fleet_noise_logs(logs: list[FlightLog], entries: dict[str, ManifestEntry] | None) -> list[FlightLog]:
    """The clean logs the fleet's noise is estimated from: those the filter can replay (an IMU of at
    least ``MIN_REPLAY_IMU_HZ``; a telemetry log's 1 Hz IMU and its autopilot estimate at the same
    rate make the GPS look metres noisier than it is)."""
    from quadformer.logs.replay import imu_too_slow

    return [lg for lg in logs if (entries is None or entries.get(lg.path.name) is None or entries[lg.path.name].clean)
            and lg.imu is not None and lg.gps is not None and not imu_too_slow(lg)]


def replay_logs(read: dict[Path, FlightLog | LogError], manifest: dict[str, ManifestEntry] | None,
                config: FilterConfig, rule: PhaseRule,
                echo: Callable[[str], None]) -> tuple[list[FieldLog], list[dict[str, str]]]:
    """Every log read (``read``: path -> its FlightLog, or the error reading it) replayed, or refused
    with its reason."""
    used, refused = [], []
    for p, log in read.items():
        try:
            if isinstance(log, LogError):
                raise log
            flights, notes = log_rows(log, "ekf", config)
        except (LogError, ValueError) as e:
            reason = str(e)
            reason = reason[len(f"{p}: "):] if reason.startswith(f"{p}: ") else reason   # the path once
            refused.append({"log": str(p), "reason": reason})
            echo(f"  refused {p.name}: {reason}")
            continue
        rows = pd.concat([f.rows for f in flights], ignore_index=True)
        phase = phases(rows["t"].to_numpy(dtype=float), log.events, log_height(log), rule, log_impacts(log))
        entry = None if manifest is None else manifest.get(p.name)
        if manifest is not None and entry is None:
            notes = [*notes, "not in the manifest: taken as a clean flight"]
        used.append(FieldLog(p, log, entry, rows, phase, notes))
        air = float(np.mean(phase == "air")) if len(phase) else 0.0
        kind = "clean" if used[-1].clean else "GPS trouble"
        echo(f"  read {p.name}: {len(rows)} GPS steps, {air:.0%} in air ({kind})")
    return used, refused


def _with_threshold(det, thr: float):
    d = copy.copy(det)
    d.threshold_ = float(thr)
    return d


def _air_hours(fl: FieldLog) -> float:
    """In-air flight-hours of a log: its in-air GPS steps times its own median step (a log's
    receiver rate, 1 to 10 Hz on real vehicles, is not the simulation's)."""
    t = fl.rows["t"].to_numpy(dtype=float)
    step = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    return float(np.sum(fl.phase == "air")) * step / 3600.0


def calibrated_thresholds(scores: dict[int, np.ndarray], logs: list[FieldLog], per_hour: float, det=None,
                          rate: float = 10.0) -> dict[int, float]:
    """Per log, the threshold of the clean logs of the other vehicles at ``per_hour``: the scored
    log's vehicle is left out of its calibration. With ``det``, the budget counts what the false-
    alarm figure counts, spoofing alerts in the air (``spoofing_budget``: an alarm the receiver's
    trouble, a landing or the ground explains is not a spoofing false alarm); without, alarm runs
    in the air (``detectors.calibration.budget_threshold``)."""
    clean = [i for i, fl in enumerate(logs) if fl.clean and i in scores]
    out: dict[int, float] = {}
    done: dict[tuple[int, ...], float] = {}
    for i in scores:
        others = tuple(j for j in clean if logs[j].vehicle != logs[i].vehicle)
        if others in done:
            out[i] = done[others]
            continue
        hours = sum(_air_hours(logs[j]) for j in others)
        if not others or hours <= 0:
            out[i] = done[others] = float("nan")
            continue
        if det is not None:
            out[i] = done[others] = spoofing_budget({j: scores[j] for j in others}, logs, hours, per_hour, det, rate)
            continue
        s, fid = [], []
        for j in others:
            air = logs[j].phase == "air"
            s.append(scores[j][air])
            fid.append(logs[j].rows["flight_id"].to_numpy()[air] + 1000 * j)
        s, fid = np.concatenate(s), np.concatenate(fid)
        out[i] = done[others] = budget_threshold(s, fid, np.unique(fid), hours, per_hour)
    return out


def spoofing_budget(scores: dict[int, np.ndarray], logs: list[FieldLog], hours: float, per_hour: float, det,
                    rate: float) -> float:
    """The lowest threshold (one of the scores in the air) at which the clean logs ``scores`` (log
    index -> scores) raise at most ``per_hour * hours`` spoofing alerts in the air, as ``detect``
    raises them (``log_alerts``); found by bisection over the candidates, the count taken as
    falling with the threshold."""
    allowed = int(np.floor(per_hour * hours))
    cands = np.unique(np.concatenate([s[logs[j].phase == "air"] for j, s in scores.items()]))
    cands = cands[np.isfinite(cands)]
    if not len(cands):
        return float("inf")

    def count(thr: float) -> int:
        d = _with_threshold(det, thr)
        return sum(clean_counts(log_alerts(logs[j], logs[j].rows, s, d, rate), 0.0)["spoofing_air"]
                   for j, s in scores.items())

    lo, hi = 0, len(cands) - 1                  # count(cands[hi]) == 0: no alarm above the largest score
    while lo < hi:
        mid = (lo + hi) // 2
        if count(float(cands[mid])) <= allowed:
            hi = mid
        else:
            lo = mid + 1
    return float(cands[lo])


def floors(logs: list[FieldLog], per_hour: float) -> dict[str, dict[str, Any]]:
    """Each clean log's physical floor (``logs.noise.detection_floor``) at ``per_hour``, by log name
    (an entry with ``reason`` where it cannot be computed)."""
    from quadformer.logs.noise import detection_floor
    from quadformer.logs.replay import in_air

    out: dict[str, dict[str, Any]] = {}
    for fl in logs:
        if not fl.clean:
            continue
        g = fl.log.gps
        f = None if g is None else detection_floor(fl.log, in_air(fl.log, g["t"].to_numpy()) > 0, per_hour)
        out[fl.path.name] = ({"vehicle": fl.vehicle, **f.to_dict()} if f is not None else
                             {"vehicle": fl.vehicle, "reason": "no GPS, IMU and attitude in the air to estimate it"})
    return out


def clean_counts(alerts: list, hours: float) -> dict[str, Any]:
    air = [a for a in alerts if a.kind == "spoofing" and a.phase == "air"]
    return {"air_hours": hours, "spoofing_air": len(air),
            "spoofing_ground": sum(a.kind == "spoofing" and a.phase == "ground" for a in alerts),
            "spoofing_transition": sum(a.kind == "spoofing" and a.phase == "transition" for a in alerts),
            "degraded": sum(a.kind == "degraded" for a in alerts)}


def trouble_counts(fl: FieldLog, alerts: list) -> dict[str, Any]:
    wins = fl.windows()

    def inside(a) -> bool:
        end = a.end_s if a.end_s is not None else np.inf
        return any(a.start_s <= b and end >= s for s, b in wins)

    return {"windows": len(wins),
            "in_window_degraded": sum(inside(a) and a.kind == "degraded" for a in alerts),
            "in_window_spoofing": sum(inside(a) and a.kind == "spoofing" for a in alerts),
            # by phase, as on the clean logs: in the air, and apart on the ground or in a transition
            "in_window_spoofing_air": sum(inside(a) and a.kind == "spoofing" and a.phase == "air" for a in alerts),
            "in_window_spoofing_transition": sum(inside(a) and a.kind == "spoofing" and a.phase == "transition"
                                                 for a in alerts),
            "outside_spoofing_air": sum(not inside(a) and a.kind == "spoofing" and a.phase == "air" for a in alerts)}


def receiver_coverage(fl: FieldLog, alerts: list) -> list[dict[str, Any]]:
    """Each trouble window's first sign: the first degraded alert open within DEGRADED_WITHIN_S of it."""
    out = []
    degraded = [a for a in alerts if a.kind == "degraded"]
    for sign in fl.signs():
        hit = [a for a in degraded if a.start_s <= sign + DEGRADED_WITHIN_S
               and (a.end_s is None or a.end_s >= sign - 1.0)]
        first = min((a.start_s for a in hit), default=None)
        out.append({"sign_s": sign - fl.gps_t0, "covered": bool(hit),
                    "delay_s": None if first is None else max(first - sign, 0.0)})
    return out


def run_field(paths: list[Path], out: Path, plan: FieldPlan, manifest: Path | None = None,
              echo: Callable[[str], None] = print, shipped: str | None = None) -> dict[str, Any]:
    """The field benchmark (see the module text); writes ``out``/results.json, tables and report.html.

    ``shipped``: a shipped set's detectors (``detectors.pretrained``; its ``ekf`` sensors) are judged
    instead of tuning ``plan.methods``: nothing is simulated or tuned, the logs are replayed with
    the filter tuning of the simulation they learned from, and their ``sim`` threshold is the
    shipped validation-F1 one."""
    from quadformer.logs.noise import estimate_noise
    from quadformer.report.field import clean_summary, injection_summary, trouble_summary, write_field_report

    t_start = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    entries = read_manifest(manifest) if manifest is not None else None
    paths = [Path(p) for p in paths]
    echo(f"reading {len(paths)} logs")
    read: dict[Path, FlightLog | LogError] = {}
    for p in paths:
        try:
            read[p] = read_log(p)
        except LogError as e:
            read[p] = e
    clean0 = fleet_noise_logs([lg for lg in read.values() if isinstance(lg, FlightLog)], entries)
    if not clean0:
        raise LogError("no clean log with an IMU fast enough for the filter could be read: the fleet noise and "
                       "the false-alarm counts need such flights")
    noise = estimate_noise(clean0)
    trained = None
    if shipped is not None:
        trained, sim = shipped_detectors(shipped)
        plan = dataclasses.replace(plan, methods=tuple(trained))
        cfg = SimConfig.from_dict(sim)
    else:
        cfg = plan.sim_config(noise.sim_overrides())
    config = FilterConfig.matching(dataclasses.asdict(cfg))
    logs, refused = replay_logs(read, entries, config, plan.phase, echo)
    if not any(fl.clean for fl in logs):
        raise LogError("no clean log could be replayed (see the refusals above)")
    if trained is None:
        echo(f"tuning {len(plan.methods)} methods on {cfg.flights} simulated flights (fleet noise from "
             f"{len(clean0)} clean logs)")
        trained = tune_methods(plan, cfg, out, echo)
    else:
        echo(f"the shipped {shipped} detectors: {', '.join(trained)} (nothing tuned)")
    rate = config.gps_rate_hz
    results: dict[str, Any] = {"plan": dataclasses.asdict(plan), "sim_config": dataclasses.asdict(cfg),
                               "noise": noise.to_dict(), "manifest": None if manifest is None else str(manifest),
                               "read": [{"log": str(fl.path), "clean": fl.clean, "steps": len(fl.rows),
                                         "air_hours": _air_hours(fl), "phase_source": _phase_source(fl),
                                         "notes": fl.notes} for fl in logs],
                               "refused": refused, "methods": {}, "versions": package_versions(),
                               "provenance": provenance({"plan": plan.seed}, "field"),
                               "shipped": shipped, "shipped_files": shipped_files(shipped) if shipped else None}
    per_log_rows, inj_rows = [], []
    receiver_rows: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    injected = {i: inject(plan, fl, i, config) for i, fl in enumerate(logs) if fl.clean}
    results["floors"] = floors(logs, plan.budget_per_hour)
    results["vehicles"] = {fl.path.name: fl.vehicle for fl in logs}
    echo(f"  {sum(map(len, injected.values()))} spoofs injected into {len(injected)} clean logs in air "
         f"({time.perf_counter() - t0:.0f} s)")
    unscored: dict[str, list[dict[str, str]]] = {}
    covered: set[int] = set()
    for m, det in trained.items():
        t0 = time.perf_counter()
        usable = {}
        for i, fl in enumerate(logs):
            lacking = missing_features(det.features_, fl.rows.columns)
            if lacking:
                unscored.setdefault(m, []).append({"log": fl.path.name, "reason": "the log's residues lack "
                                                   + ", ".join(lacking)})
            else:
                usable[i] = fl
        scores = {i: np.asarray(det.decision_function(fl.rows), dtype=float) for i, fl in usable.items()}
        cal = calibrated_thresholds(scores, logs, plan.budget_per_hour, det, rate)
        dets_by_log = {i: {"sim": det, **({"calibrated": _with_threshold(det, cal[i])} if np.isfinite(cal[i]) else {})}
                       for i in usable}
        for i, fl in usable.items():
            for thr_name, d in dets_by_log[i].items():
                alerts = log_alerts(fl, fl.rows, scores[i], d, rate)
                row = {"method": m, "threshold": thr_name, "log": fl.path.name, "clean": fl.clean,
                       "threshold_value": float(d.threshold_), **clean_counts(alerts, _air_hours(fl))}
                if not fl.clean:
                    row.update(trouble_counts(fl, alerts))
                per_log_rows.append(row)
                if i not in covered and fl.signs():          # the receiver's alerts: the same for every method
                    covered.add(i)
                    receiver_rows += [{"log": fl.path.name, **c} for c in receiver_coverage(fl, alerts)]
            if fl.clean:
                inj_rows += injected_events(fl, injected[i], m, dets_by_log[i], rate,
                                            results["floors"].get(fl.path.name))
        echo(f"  {m}: scored in {time.perf_counter() - t0:.0f} s")
    per_log = pd.DataFrame(per_log_rows)
    inj = pd.DataFrame(inj_rows)
    summary = clean_summary(per_log)
    inj_sum = injection_summary(inj) if len(inj) else pd.DataFrame()
    results["false_alarms"] = summary.to_dict(orient="records")
    results["injection"] = inj_sum.to_dict(orient="records")
    results["receiver"] = receiver_rows
    results["troubles"] = trouble_summary(per_log).to_dict(orient="records")
    results["unscored"] = unscored
    results["timing_s"] = time.perf_counter() - t_start
    per_log.to_csv(out / "per_log.csv", index=False)
    inj.to_csv(out / "injections.csv", index=False)
    write_json(out / "results.json", results)
    write_field_report(results, per_log, inj, example_traces(plan, logs, trained, rate, config), out / "report.html")
    echo(f"field benchmark took {results['timing_s']:.0f} s; report in {out / 'report.html'}")
    return results


def _trace(title: str, fl: FieldLog, rows: pd.DataFrame, phase: np.ndarray, det, rate: float,
           attack: tuple[float, float] | None = None) -> dict[str, Any]:
    s = np.asarray(det.decision_function(rows), dtype=float)
    alerts = log_alerts(fl, rows, s, det, rate)
    return {"title": title, "t": rows["t"].to_numpy(dtype=float), "score": s, "threshold": float(det.threshold_),
            "phase": phase, "windows": fl.windows(), "attack": attack,
            "alerts": [{"start_s": a.start_s, "kind": a.kind, "phase": a.phase} for a in alerts]}


def example_traces(plan: FieldPlan, logs: list[FieldLog], trained: dict[str, Any], rate: float,
                   config: FilterConfig) -> list[dict[str, Any]]:
    """One example flight per kind of log (clean, with GPS trouble, a clean one with a spoof injected),
    scored by QUADFormer where it ran (else the first method) at the simulation's threshold."""
    m = "quadformer" if "quadformer" in trained else next(iter(trained))
    det = trained[m]
    out = []
    scored = [(li, fl) for li, fl in enumerate(logs) if not missing_features(det.features_, fl.rows.columns)]
    clean = sorted((fl for _, fl in scored if fl.clean), key=lambda fl: -_air_hours(fl))
    bad = sorted((fl for _, fl in scored if not fl.clean), key=lambda fl: -len(fl.signs()))
    if clean:
        fl = clean[0]
        out.append(_trace(f"{m} on a clean flight: {fl.path.name} (ground grey, take-off transition yellow; "
                          "alerts red = spoofing, purple = degraded)", fl, fl.rows, fl.phase, det, rate))
    if bad:
        fl = bad[0]
        out.append(_trace(f"{m} on a flight with GPS trouble: {fl.path.name} (manifest windows pink)", fl, fl.rows,
                          fl.phase, det, rate))
    for li, fl in scored:
        inj = planned_injections(plan, fl, li, "bias") if fl.clean else {}
        if inj:
            seg, (t0, batches) = next(iter(inj.items()))
            b = batches[0]
            f = ekf_flights(fl.log, seg, config, [b])[0]
            phase = phases(f.rows["t"].to_numpy(dtype=float), fl.log.events, log_height(fl.log), plan.phase,
                           log_impacts(fl.log))
            out.append(_trace(f"{m} on {fl.path.name} with a {float(b.magnitude[0]):.1f} m bias injected (green)",
                              fl, f.rows, phase, det, rate, (float(b.onset[0]) + t0, float(b.end[0]) + t0)))
            break
    return out


def _phase_source(fl: FieldLog) -> str:
    ev = fl.log.events
    if ev is not None and ev["event"].isin(["takeoff", "landed"]).any():
        return "events"
    return "height" if log_height(fl.log) is not None else "none"
