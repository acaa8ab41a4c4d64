"""Detection on a flight log and a dataset from flight logs.

``detect_log``: read a log, turn each segment into rows of the flight table (``replay``),
score them with a fitted, calibrated detector and raise its alerts through the online step.
``logs_dataset``: the rows of many logs (optionally with injected spoofs, labelled) as a
dataset in the project's format, which ``benchmark --data``, ``fit`` and ``evaluate`` take.
"""

from __future__ import annotations

import dataclasses
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from quadformer.logs import FORMAT_OF_SOURCE, read_log
from quadformer.logs.flightlog import FlightLog, LogError
from quadformer.estimator.filter_config import FilterConfig
from quadformer.estimator.schema import GROUPS
from quadformer.logs.replay import (RESIDUE_SOURCES, LogFlight, autopilot_rows, ekf_flights, ekf_rows, imu_too_slow,
                                    log_height, log_sensors, missing_features, no_innovations)

MIN_DETECT_S = 1.0   # s, a segment shorter than this is not scored


class DetectorInputError(ValueError):
    """A detector that needs residue columns a log's residues do not provide."""


class NothingToScore(LogError):
    """A readable log with nothing to score (no GPS, too short a segment): ``log`` holds it."""

    def __init__(self, message: str, log: FlightLog):
        super().__init__(message)
        self.log = log


@dataclass
class LogDetection:
    log: FlightLog
    residues: str
    rows: pd.DataFrame                 # the flight table of every replayed segment (flight_id: segment)
    scores: np.ndarray
    alarms: np.ndarray
    alerts: list
    sensors: str
    detector: Any
    notes: list[str] = field(default_factory=list)   # what the replay did, segments skipped and why


def log_rows(log: FlightLog, residues: str = "ekf", config: FilterConfig = FilterConfig(),
             attacks: dict[int, Any] | None = None) -> tuple[list[LogFlight], list[str]]:
    """Every usable segment of ``log`` as rows; (flights, notes on the segments skipped).
    ``attacks``: segment index -> one-flight ``AttackBatch`` to inject (``ekf`` only)."""
    if residues not in RESIDUE_SOURCES:
        raise ValueError(f"residues: unknown source {residues!r}; choose from {', '.join(RESIDUE_SOURCES)}")
    if attacks and residues != "ekf":
        raise ValueError("injection needs --residues ekf: the autopilot's logged innovations cannot see a "
                         "spoof added afterwards")
    if residues == "ekf" and log.gps is not None and imu_too_slow(log):    # the whole log, not its slivers
        raise LogError(f"{log.path}: {imu_too_slow(log)}"
                       + ("; use --residues autopilot for the autopilot's logged innovations"
                          if log.innovations is not None else " (the log holds no GPS innovations of the "
                          "autopilot's either: nothing can score it)"))
    if residues == "autopilot" and log.gps is not None and (log.innovations is None or not len(log.innovations)):
        raise LogError(no_innovations(log))
    flights, notes = [], []
    for seg in range(len(log.segments)):
        try:
            if residues == "ekf":
                f = ekf_rows(log, seg, config, attack=(attacks or {}).get(seg))
            else:
                f = LogFlight(seg, autopilot_rows(log, seg), "autopilot")
        except LogError as e:
            if len(log.segments) == 1:
                raise
            notes.append(f"segment {seg} skipped: {e}")
            continue
        flights.append(f)
        notes += [f"segment {seg}: {n}" for n in f.notes]
    if not flights:
        raise LogError(f"{log.path}: no segment could be replayed: " + "; ".join(notes))
    return flights, notes


def detect_log(log: FlightLog | str | Path, detector=None, residues: str = "ekf",
               config: FilterConfig | None = None, format: str | None = None,
               typing: str = "shape") -> LogDetection:
    """Scores, alarms and alerts of a calibrated ``detector`` on every segment of ``log``;
    ``typing``: where the alerts' attack types come from (``detectors.attack_types.TYPINGS``).

    Without a ``detector``, the shipped one that fits the log's sensors and ``residues``
    (``shipped_for``), at its false-alarm-budget threshold, replayed with the filter tuning of
    the simulation it learned from (``config`` overrides it). ``config`` None with a detector:
    EKF2's defaults (``FilterConfig()``)."""
    if not isinstance(log, FlightLog):
        log = read_log(log, format=format)
    if detector is None:
        detector, matched = shipped_for(log, residues)
        config = matched if config is None else config
    config = FilterConfig() if config is None else config
    if getattr(detector, "threshold_", None) is None:
        raise ValueError(f"{detector.name}: no alarm threshold; use a model written by `quadformer fit`")
    try:
        flights, notes = log_rows(log, residues, config)
    except LogError as e:
        raise NothingToScore(str(e), log) from None
    from quadformer.logs.vehicle import check_profile

    try:
        check_profile(detector, log, flights[0].sensors)      # a vehicle profile: this vehicle's logs only
    except LogError as e:
        raise NothingToScore(str(e), log) from None
    rows = pd.concat([f.rows for f in flights], ignore_index=True)
    lacking = missing_features(detector.features_, rows.columns)
    if lacking:
        have = sorted({c.rsplit("_", 1)[0] if not c.endswith("nis") else c for c in rows.columns
                       if c.startswith("res_")})
        if residues == "autopilot" and log.imu is not None and log.gps is not None:
            fix = "use --residues ekf (the project's filter replayed over this log's IMU and GPS gives them)"
        elif residues == "autopilot":
            fix = ("fit a detector on the GPS innovation columns alone (e.g. quadformer fit --method chi2), "
                   "the only ones an autopilot logs")
        else:
            fix = ("fit a detector on data of this log's sensor configuration (quadformer simulate --sensors "
                   f"{flights[0].sensors})")
        raise DetectorInputError(
            f"{log.path}: detector {detector.name} reads {', '.join(lacking)}, which the {residues!r} residues "
            f"of this log do not provide (they hold {', '.join(have) or 'nothing'}); {fix}")
    scores = detector.decision_function(rows)
    alarms = scores > detector.threshold_
    impacts = log_impacts(log)
    if impacts is not None and len(impacts):
        notes = [*notes, impacts_note(impacts)]
    alerts = step_alerts(rows, scores, detector, typing, config.gps_rate_hz, events=log.events,
                         receiver=log.receiver, height=log_height(log), impacts=impacts)
    return LogDetection(log, residues, rows, scores, alarms, alerts, flights[0].sensors, detector, notes)


def shipped_for(log: FlightLog, residues: str = "ekf", threshold: str = "budget"):
    """(detector, filter tuning): the shipped detector that fits ``log``'s sensors and
    ``residues`` (``detectors.pretrained.choose``), alarming at its ``threshold``, and the
    filter tuning of the simulation it learned from, fusing the sensors of its set the log has
    (each log of a run its own)."""
    from quadformer.detectors import pretrained

    have = set(log_sensors(log))
    entry = pretrained.choose(have, residues, FORMAT_OF_SOURCE.get(log.source))
    det = pretrained.load(entry.name, threshold=threshold)
    sim = (getattr(det, "calibration_", None) or {}).get("sim_config")
    over = {"sensors": entry.set.sensors, "sensors_where_logged": True} if entry.set.residues == "ekf" else {}
    return det, (FilterConfig.matching(sim, **over) if sim else FilterConfig(**over))


def log_impacts(log: FlightLog) -> pd.DataFrame | None:
    """The impacts in the log's IMU (``detectors.impact.impacts``: columns t, event, detail, g,
    crash), for its flight phase's landings; None without an IMU."""
    from quadformer.detectors.impact import impacts

    return impacts(log.imu) if log.imu is not None and len(log.imu) else None


def impacts_note(impacts: pd.DataFrame, most: int = 8) -> str:
    """The impacts of a log in a note: ``imu: 2 impact(s) at 19.9 s (impact: 3.3 g), ...``."""
    listed = ", ".join(f"{r.t:.1f} s ({r.detail})" for r in impacts.head(most).itertuples())
    more = f" and {len(impacts) - most} more" if len(impacts) > most else ""
    return (f"imu: {len(impacts)} impact(s) at {listed}{more}; a crash, or an impact near the ground, is a landing "
            "(its 10 s before and 5 s after are a transition)")


def step_alerts(rows: pd.DataFrame, scores: np.ndarray, detector, typing: str = "shape",
                gps_rate_hz: float = FilterConfig.gps_rate_hz, events: pd.DataFrame | None = None,
                receiver: pd.DataFrame | None = None, height: pd.DataFrame | None = None,
                impacts: pd.DataFrame | None = None) -> list:
    """The alerts of ``rows`` (flights by ``flight_id``) scored in one batch (``scores``): each
    flight's rows driven through the online step (``resilience.step.OnlineStep``) that the live
    monitor and the closed loop drive, so its alert lifecycle, onsets and shape typing are the
    live ones. The replayed filter fused every fix, so the step decides no GPS admission here.

    With the vehicle's ``events`` (columns t, event, detail), the receiver's status reports
    (``receiver``: columns t, fix_type and any of satellites, eph, epv, speed_acc, jamming, noise,
    spoofing), ``height`` (columns t, h) or ``impacts`` (columns t, crash, detail:
    ``log_impacts``), each flight's step gets a ``FlightPhase`` and a ``ReceiverHealth`` that
    label its alerts, and they are fed, in time order (at equal times: events, reports, heights,
    impacts), everything up to each row's time before that row; what remains after a flight's
    last row (up to the next flight's first row, or the end) before its ``finish``. A flight's
    phase is fed the log from its start; its health from its first row (the first flight's from
    the log's start), so a degraded episode is raised by one flight only. A landing relabels the
    alerts raised in the air in its ``land_s`` before (``OnlineStep``), so they end as
    ``transition``, as ``flight_phase.phases`` labels those steps."""
    from quadformer.detectors import flight_slices
    from quadformer.detectors.alarms import onset_flags
    from quadformer.detectors.attack_types import RESET_COLUMNS, TYPING_COLUMNS, OnlineTyper, alert_typer
    from quadformer.detectors.flight_phase import FlightPhase, timeline
    from quadformer.detectors.receiver_health import REPORT_FIELDS, ReceiverHealth
    from quadformer.detectors.streams import ScoredStream
    from quadformer.resilience.step import OnlineStep

    labelled = any(f is not None for f in (events, receiver, height, impacts))
    _check_columns(events, receiver, height, impacts)
    alarms = np.asarray(scores) > detector.threshold_
    if not alarms.any() and receiver is None and events is None:    # nothing can raise an alert
        return []
    shape = alert_typer(rows, typing)
    types = None
    if shape is None and hasattr(detector, "predict_type"):
        types = np.asarray(detector.predict_type(rows), dtype=object)
    above = onset_flags(rows, detector)
    typed = [c for c in (*TYPING_COLUMNS[1:], *RESET_COLUMNS) if c in rows.columns] if shape is not None else []
    # the raw GPS innovation: whether the fix moves against the IMU (a receiver's capture)
    typed += [c for c in GROUPS["res_gps_r"].columns if c in rows.columns and c not in typed]
    t = rows["t"].to_numpy(dtype=float)
    items = list(timeline(("events", events), ("receiver", receiver), ("height", height),
                          ("impacts", impacts))) if labelled else []
    fields = [c for c in REPORT_FIELDS if receiver is not None and c in receiver.columns]
    slices = flight_slices(rows)
    starts = sorted(t[idx[0]] for _, idx in slices)
    alerts = []
    for fid, idx in slices:
        stream = ScoredStream(scores[idx], alarms[idx], None if types is None else types[idx],
                              None if above is None else above[idx])
        step = OnlineStep(stream, flight_ids=[fid], typer=None if shape is None else OnlineTyper(shape, gps_rate_hz),
                          phase=FlightPhase() if labelled else None,
                          health=ReceiverHealth(flight_id=fid) if labelled else None)
        before = t[idx[0]] if starts[0] < t[idx[0]] else -np.inf      # earlier: the flight before's
        after = min((s for s in starts if s > t[idx[0]]), default=np.inf)
        pending = deque(items)
        values = rows[typed].to_numpy(dtype=float)[idx]
        for k_row in range(len(idx)):
            _feed(step, pending, t[idx[k_row]], before, fields)
            step.update_columns(t[idx[k_row]], dict(zip(typed, values[k_row, :, None])))
        _feed(step, pending, after, before, fields, inclusive=False)
        step.finish()
        alerts += step.alerts
    return alerts


def _feed(step, pending: deque, until: float, before: float, fields: list[str], inclusive: bool = True) -> None:
    """Feed ``step`` the pending (t, source, row) items up to ``until`` (inclusive or not), in
    order: an item before ``before`` (the flight before's) to its flight phase only."""
    while pending and (pending[0][0] <= until if inclusive else pending[0][0] < until):
        ti, name, row = pending.popleft()
        if ti < before:
            if name == "events":
                step.phase.event(ti, str(row["event"]))
            elif name == "height":
                step.phase.update(ti, float(row["h"]))
            elif name == "impacts":
                step.phase.impact(ti, bool(row["crash"]), str(row.get("detail", "impact")))
        elif name == "events":
            step.event(ti, str(row["event"]))
        elif name == "receiver":
            step.receiver(ti, **{c: row[c] for c in fields})
        elif name == "height":
            step.height(ti, float(row["h"]))
        else:
            step.impact(ti, bool(row["crash"]), str(row.get("detail", "impact")))


def _check_columns(events: pd.DataFrame | None, receiver: pd.DataFrame | None, height: pd.DataFrame | None,
                   impacts: pd.DataFrame | None = None) -> None:
    for name, frame, need in (("events", events, ("t", "event")), ("receiver", receiver, ("t", "fix_type")),
                              ("height", height, ("t", "h")), ("impacts", impacts, ("t", "crash"))):
        if frame is not None and not set(need) <= set(frame.columns):
            raise ValueError(f"{name}: columns {', '.join(c for c in need if c not in frame.columns)} missing "
                             f"(has {', '.join(map(str, frame.columns)) or 'none'})")


def logs_dataset(paths: list[Path], residues: str = "ekf", config: FilterConfig = FilterConfig(),
                 attack=None, seed: int = 0, format: str | None = None, repeat: int = 1,
                 progress=None, group: bool = True):
    """A dataset of the segments of ``paths`` (each replayed ``repeat`` times): one flight
    per segment and repetition, the repetitions of a segment in one ``group`` (the split keeps
    a group together; ``group=False`` leaves the groups out, so the split treats every replay as
    a flight of its own, which puts replays of one recording in training and test: for small
    fleets only, and optimistic). ``attack``: an ``AttackConfig`` injected on its ``fraction``
    of the flights (which flights, and each attack's parameters, drawn from ``seed`` as in
    the simulator); onsets are drawn within each flight (``onset`` clipped to its first
    half). Returns (dataset, per-log notes)."""
    from quadformer.attacks import sample_attacks
    from quadformer.dataset import Dataset, summarize
    from quadformer.io import package_versions
    from quadformer.rng import Stream, attacked_flights, flight_generator

    if repeat < 1:
        raise ValueError(f"repeat must be >= 1, got {repeat}")
    if attack is not None and residues != "ekf":
        raise ValueError("injection needs --residues ekf: the autopilot's logged innovations cannot see a "
                         "spoof added afterwards")
    logs = []
    for p in paths:
        logs.append(read_log(p, format=format))
        if progress is not None:
            progress(1)
    # one flight per (log, segment, repetition); attacks drawn per flight index
    units = [(li, seg) for li, log in enumerate(logs) for seg in range(len(log.segments))]
    units = [u for u in units for _ in range(repeat)]
    attacked = attacked_flights(seed, len(units), attack.fraction if attack is not None else 0.0)
    frames, scen, notes = [], [], {str(p): [] for p in paths}
    batches = []
    for k, (li, seg) in enumerate(units):
        batch = None
        if attack is not None and attacked[k]:
            dur = logs[li].segments[seg][1] - logs[li].segments[seg][0]
            onset = (min(attack.onset[0], 0.5 * dur), min(attack.onset[1], 0.5 * dur))
            batch = sample_attacks([flight_generator(seed, k, Stream.SCENARIO)],
                                   dataclasses.replace(attack, onset=onset), np.ones(1, bool), dur)
        batches.append(batch)
    fid = 0
    for start in range(0, len(units), repeat):       # the repetitions of one segment, replayed together
        li, seg = units[start]
        log, ks = logs[li], range(start, start + repeat)
        try:
            if residues == "ekf":
                flights = ekf_flights(log, seg, config, [batches[k] for k in ks])
            else:
                flights = [LogFlight(seg, autopilot_rows(log, seg), "autopilot")] * repeat
        except LogError as e:
            notes[str(paths[li])].append(f"segment {seg} skipped: {e}")
            continue
        notes[str(paths[li])] += [f"segment {seg}: {n}" for n in flights[0].notes] if start % repeat == 0 else []
        for k, f in zip(ks, flights):
            batch = batches[k]
            rows = f.rows.assign(flight_id=np.int32(fid))
            frames.append(rows)
            row = {"flight_id": fid, **({"group": f"{paths[li]}#{seg}"} if group else {}),
                   "attacked": bool(batch is not None and rows.label.any()),
                   "attack_type": str(batch.kind[0]) if batch is not None else "none", "log": str(paths[li]),
                   "segment": seg,
                   "repeat": k - start, "duration": float(rows.t.iloc[-1] - rows.t.iloc[0]), "sensors": f.sensors}
            if batch is not None:
                row.update(onset=float(batch.onset[0]), end=float(batch.end[0]), magnitude=float(batch.magnitude[0]),
                           rate=float(batch.rate[0]), attack_axes=str(batch.axes[0]))
            scen.append(row)
            fid += 1
    if not frames:
        raise LogError("no flight could be made from these logs: " + "; ".join(
            f"{p}: {', '.join(n)}" for p, n in notes.items() if n))
    flights = pd.concat(frames, ignore_index=True)
    flights["attack_type"] = flights["attack_type"].astype("string")
    scenarios = pd.DataFrame(scen)
    meta = {"format_version": 2, "source": "logs", "logs": [str(p) for p in paths], "residues": residues,
            "replay": dataclasses.asdict(config), "gps_rate_hz": config.gps_rate_hz, "seed": seed,
            "repeat": repeat, "grouped": group, "attack": None if attack is None else dataclasses.asdict(attack),
            "notes": notes, "versions": package_versions(), "summary": summarize(flights, scenarios)}
    return Dataset(flights, scenarios, meta)
