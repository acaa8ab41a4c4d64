"""Alarm runs and alert events: a detector's alarms as an operator or an autopilot sees them.

One alert per run of consecutive alarmed steps of a flight: when it was raised, the
estimated onset of the attack (from the detector's onset criterion where it has one, else
the alarm time), its attack type (from a typer such as ``attack_types.ShapeTyper`` where
one is given, else from the detector where it classifies, else ``attack``), the peak score
during the run and when the run ended (``None`` while still alarmed at the end of the data).
An alert also carries its kind (``spoofing``, or ``degraded`` when raised while the receiver
was degraded: ``detectors.receiver_health``), the flight phase at its raise (``ground``,
``transition`` or ``air``: ``detectors.flight_phase``) and the reason for a kind that is not
the detector's own say; ``alert_counts`` counts them apart (the headline: spoofing in the air).
The phase of an alert raised in the air shortly before a landing is known only at the landing:
the online step then relabels it (an ``alert_relabel`` event, ``AlertTracker.relabel``).

``AlertTracker`` is that lifecycle (raise, estimated onset, confirm the type, close) fed one
step at a time; the live monitor, the closed loop and offline scoring (``alerts_from_scores``)
all run it, so one flight gives the same alerts by every route.
"""

from __future__ import annotations

import dataclasses
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import pandas as pd

from quadformer.detectors.base import flight_slices
from quadformer.detectors.runs import runs
from quadformer.io import atomic_path

ALERT_COLUMNS = ["flight_id", "start_s", "onset_s", "attack_type", "score", "end_s", "confirmed_type",
                 "kind", "phase", "reason"]
ALERT_EVENTS = ("alert_start", "alert_end", "alert_type", "alert_relabel")
ALERT_KINDS = ("spoofing", "degraded")
#: a flight phase in words, as alerts and the live monitor say it
PHASE_WORDS = {"ground": "on the ground", "transition": "in the take-off transition", "air": "in the air"}
LANDING = "landing at t="      # how a landing transition's reason says the landing (flight_phase.Landing)


def phase_words(phase: str, reason: str | None = None) -> str:
    """An alert's flight phase in words: ``PHASE_WORDS``, and "in the landing transition" for a
    transition whose reason names a landing."""
    if phase == "transition" and reason is not None and LANDING in reason:
        return "in the landing transition"
    return PHASE_WORDS.get(phase, phase)


def with_reason(reason: str | None, more: str | None) -> str | None:
    """Two reasons as one (``"fix lost (fix type 1); landing at t=93.0 s (height)"``)."""
    if more is None or (reason is not None and more in reason):
        return reason
    return more if reason is None else f"{reason}; {more}"


def run_starts(X: pd.DataFrame, alarms: np.ndarray) -> np.ndarray:
    """Boolean mask of the rows of X where an alarm run of a flight starts."""
    alarms = np.asarray(alarms, dtype=bool)
    out = np.zeros(len(alarms), dtype=bool)
    for _, idx in flight_slices(X):
        for s, _ in runs(alarms[idx]):
            out[idx[s]] = True
    return out


@dataclass(frozen=True)
class Alert:
    flight_id: Any
    start_s: float           # time of the first alarmed step
    onset_s: float           # estimated attack onset (<= start_s)
    attack_type: str
    score: float             # peak score during the alarm run
    end_s: float | None      # time of the first step after the run (None: still alarmed)
    confirmed_type: str | None = None   # the shape typer's type confirm_s after the start (None: not typed by shape)
    kind: str = "spoofing"   # "spoofing", or "degraded": raised while the receiver was degraded, or its episode
    phase: str = "air"       # the flight phase at the raise (detectors.flight_phase.PHASES)
    reason: str | None = None   # why it is of its kind where something other than the detector said so

    def __str__(self) -> str:
        end = f"{self.end_s:.1f} s" if self.end_s is not None else "open"
        what = f"{self.attack_type} alert" if self.kind == "spoofing" else f"{self.kind} alert"
        if self.kind != "spoofing" and self.attack_type != "none":
            what += f" ({self.attack_type})"
        peak = f", peak score {self.score:.3g}" if np.isfinite(self.score) else ""
        confirmed = f", confirmed {self.confirmed_type}" if self.confirmed_type is not None else ""
        reason = f"; {self.reason}" if self.reason is not None else ""
        where = phase_words(self.phase, self.reason)
        return (f"flight {self.flight_id}: {what} at {self.start_s:.1f} s {where} "
                f"(onset ~{self.onset_s:.1f} s, until {end}{peak}{confirmed}{reason})")


@dataclass(frozen=True)
class AlertEvent:
    """A change in an alert's life: ``alert_start`` (raised), ``alert_end`` (closed; ``alert.end_s``
    None when the data ended under it), ``alert_type`` (its type confirmed; ``raised_as`` the
    type it was raised with) or ``alert_relabel`` (its flight phase corrected once a landing was
    seen, ``was`` the phase it had; or its kind, ``was_kind`` the kind it had, where that changed).
    ``flight``: the flight's position in the tracker's batch;
    ``t``: the step's time (None for the close at the end of the data); ``step``: the step's index."""
    event: str
    flight: int
    t: float | None
    alert: Alert
    step: int = -1
    raised_as: str | None = None
    was: str | None = None
    was_kind: str | None = None


class AlertTracker:
    """The alert lifecycle of ``n`` flights stepped together (see the module text).

    ``update`` takes one step: each flight's time, score, alarm (the detector's rule), the type,
    kind, flight phase and reason to raise an alert with, and where the detector has an onset
    criterion, whether its raw score is above the onset level (``StreamStep.above``); the onset of
    a new alert is the first step of the run of such steps that ends just before the alarm (the
    alarm's own time otherwise), as ``onset_times`` back-tracks offline. ``confirm`` sets an
    alert's confirmed type; ``end`` closes an open alert whose alarm stands (another takes the
    alarm over); ``finish`` closes what is open at the end of the data. Closed alerts are kept in ``alerts`` (the last
    ``keep``); memory does not grow with time beyond that."""

    def __init__(self, n: int, flight_ids: Sequence[Any] | None = None, keep: int | None = None):
        if not (isinstance(n, (int, np.integer)) and n >= 1):
            raise ValueError(f"n must be an integer >= 1, got {n!r}")
        self.n = int(n)
        ids = list(range(self.n)) if flight_ids is None else [f.item() if hasattr(f, "item") else f
                                                              for f in flight_ids]
        if len(ids) != self.n:
            raise ValueError(f"{len(ids)} flight ids for {self.n} flights")
        self.flight_ids = ids
        self.open: list[Alert | None] = [None] * self.n
        self._is_open = np.zeros(self.n, dtype=bool)
        self._peak = np.full(self.n, -np.inf)
        self._rise = np.full(self.n, np.nan)      # first step time of the current run above the onset level
        self.alerts: list[Alert] = []
        self._order: list[tuple[int, int]] = []   # (flight, step) of each closed alert
        self._open_step = np.full(self.n, -1)
        self.keep = keep
        self.steps = np.zeros(self.n, dtype=np.int64)
        self.n_alerts = 0

    def update(self, t, score, alarm, attack_type=None, above=None, active=None, kind=None, phase=None,
               reason=None) -> list[AlertEvent]:
        """One step; returns its events (starts and ends). ``t``: the step's time, one value or
        one per flight; ``attack_type``: one name or one per flight (None: ``attack``); ``active``:
        the flights that have this step (all by default; offline flights of unequal length);
        ``kind``, ``phase``, ``reason``: what a new alert is raised with, one value or one per
        flight (None: ``spoofing``, ``air``, no reason)."""
        n = self.n
        t = np.broadcast_to(np.asarray(t, dtype=float), (n,))
        score = np.broadcast_to(np.asarray(score, dtype=float), (n,))
        alarm = np.broadcast_to(np.asarray(alarm, dtype=bool), (n,))
        act = np.ones(n, dtype=bool) if active is None else np.asarray(active, dtype=bool)
        events = []
        starts = np.nonzero(alarm & ~self._is_open & act)[0]
        ends = np.nonzero(~alarm & self._is_open & act)[0]
        going = alarm & self._is_open & act
        self._peak[going] = np.maximum(self._peak[going], score[going])
        for i in ends:
            events.append(self._close(int(i), float(t[i]), int(self.steps[i])))
        for i in starts:
            typed, k, ph, why = (_of(v, i) for v in (attack_type, kind, phase, reason))
            onset = self._rise[i] if np.isfinite(self._rise[i]) else t[i]
            a = Alert(self.flight_ids[i], float(t[i]), float(onset), "attack" if typed is None else str(typed),
                      float(score[i]), None, kind="spoofing" if k is None else str(k),
                      phase="air" if ph is None else str(ph), reason=None if why is None else str(why))
            self.open[i] = a
            self._is_open[i] = True
            self._peak[i] = score[i]
            self._open_step[i] = self.steps[i]
            self.n_alerts += 1
            events.append(AlertEvent("alert_start", int(i), float(t[i]), a, int(self.steps[i])))
        if above is not None:
            up = np.broadcast_to(np.asarray(above, dtype=bool), (n,)) & act
            self._rise[up & ~np.isfinite(self._rise)] = t[up & ~np.isfinite(self._rise)]
            self._rise[~up & act] = np.nan
        else:
            self._rise[act] = np.nan
        self.steps[act] += 1
        return events

    def peak(self, i: int) -> float:
        """The peak score so far of flight i's open alert (-inf when none is open)."""
        return float(self._peak[i]) if self._is_open[i] else -np.inf

    def _close(self, i: int, t: float | None, step: int) -> AlertEvent:
        a = dataclasses.replace(self.open[i], score=float(self._peak[i]), end_s=t)
        self.open[i] = None
        self._is_open[i] = False
        self.alerts.append(a)
        self._order.append((i, int(self._open_step[i])))
        if self.keep is not None and len(self.alerts) > self.keep:
            del self.alerts[0], self._order[0]
        return AlertEvent("alert_end", i, t, a, step)

    def end(self, i: int, t: float) -> AlertEvent | None:
        """Close flight i's open alert at t though its alarm stands (None: none open); a new alert,
        raised with what the next ``update`` is given, takes the alarm over from that step."""
        if not self._is_open[i]:
            return None
        return self._close(int(i), float(t), int(self.steps[i]))

    def confirm(self, i: int, start_s: float, kind: str, t: float | None = None) -> AlertEvent | None:
        """Confirm the type of flight i's alert raised at ``start_s`` (open, or among those kept)."""
        got = self._amend(i, start_s, lambda a: dataclasses.replace(a, confirmed_type=kind))
        return None if got is None else AlertEvent("alert_type", i, t, got[1], raised_as=None)

    def relabel(self, i: int, start_s: float, phase: str, reason: str | None,
                t: float | None = None, attack_type: str | None = None,
                kind: str | None = None) -> AlertEvent | None:
        """Set the flight phase of flight i's alert raised at ``start_s`` (open, or among those
        kept) and add ``reason`` to its own; with ``attack_type``, its type (and its confirmed
        type, where it has one) too; with ``kind``, its kind; the ``alert_relabel`` event (None:
        no such alert)."""
        def change(a: Alert) -> Alert:
            b = relabelled(a, phase, reason)
            if kind is not None:
                b = dataclasses.replace(b, kind=kind)
            if attack_type is None:
                return b
            return dataclasses.replace(b, attack_type=attack_type,
                                       confirmed_type=None if a.confirmed_type is None else attack_type)

        got = self._amend(i, start_s, change)
        if got is None:
            return None
        was_kind = got[0].kind if kind is not None and kind != got[0].kind else None
        return AlertEvent("alert_relabel", i, t, got[1], was=got[0].phase, was_kind=was_kind)

    def _amend(self, i: int, start_s: float, change) -> tuple[Alert, Alert] | None:
        """(before, after) of flight i's alert raised at ``start_s`` changed by ``change``."""
        a = self.open[i]
        if a is not None and a.start_s == start_s:
            self.open[i] = b = change(a)
            return a, b
        for k in range(len(self.alerts) - 1, -1, -1):
            a = self.alerts[k]
            if self._order[k][0] == i and a.start_s == start_s:
                self.alerts[k] = b = change(a)
                return a, b
        return None

    def finish(self, flights: Sequence[int] | None = None) -> list[AlertEvent]:
        """Close the open alerts (of ``flights``, all by default) at the end of the data (end_s None)."""
        idx = range(self.n) if flights is None else flights
        return [self._close(int(i), None, int(self.steps[i])) for i in idx if self._is_open[i]]

    def closed(self) -> list[tuple[int, int, Alert]]:
        """(flight, step raised at, alert) of the closed alerts kept, by flight (batch order) then time."""
        return sorted(((i, j, a) for (i, j), a in zip(self._order, self.alerts)), key=lambda x: x[:2])


def relabelled(a: Alert, phase: str, reason: str | None) -> Alert:
    """``a`` in flight phase ``phase``, ``reason`` added to its own."""
    return dataclasses.replace(a, phase=phase, reason=with_reason(a.reason, reason))


def _of(value, i: int):
    """Flight i's value of one value or one per flight (a string is one value)."""
    return value if value is None or isinstance(value, str) else value[i]


def alert_counts(alerts: Sequence[Alert]) -> dict[str, int]:
    """Alerts counted apart: ``alerts`` the spoofing alerts raised in the air (the headline),
    ``alerts_ground`` and ``alerts_transition`` the spoofing alerts raised on the ground and in
    a take-off or landing transition, ``alerts_degraded`` those of a degraded receiver (any
    phase), and ``alerts_total`` all of them."""
    spoof = [a for a in alerts if a.kind != "degraded"]
    return {"alerts": sum(a.phase == "air" for a in spoof),
            "alerts_ground": sum(a.phase == "ground" for a in spoof),
            "alerts_transition": sum(a.phase == "transition" for a in spoof),
            "alerts_degraded": len(alerts) - len(spoof), "alerts_total": len(alerts)}


def onset_flags(X: pd.DataFrame, detector) -> np.ndarray | None:
    """Per row of X, whether the detector's raw score is above its onset level (detectors with an
    onset criterion: ``raw_scores`` and ``onset_level_``), else None."""
    level = getattr(detector, "onset_level_", None) if detector is not None else None
    if level is None or not hasattr(detector, "raw_scores"):
        return None
    raw, _ = detector.raw_scores(X)
    return np.asarray(raw) > level


def track_alerts(X: pd.DataFrame, scores: np.ndarray, alarms: np.ndarray, types=None,
                 above: np.ndarray | None = None) -> tuple[list[Alert], np.ndarray]:
    """The ``AlertTracker`` over the flights of X (rows grouped by ``flight_id``, time ``t``), all
    flights stepped together; (alerts by flight and time, the row of each alert's start). Steps
    where no flight's alarm or onset flag is raised or changes leave the tracker as it is and are
    passed over."""
    slices = flight_slices(X)
    if not slices:
        return [], np.zeros(0, dtype=int)
    t = X["t"].to_numpy(dtype=float)
    lengths = np.array([len(idx) for _, idx in slices])
    first = np.array([idx[0] for _, idx in slices])
    step = np.arange(len(X)) - np.repeat(first, lengths)          # each row's step in its flight
    busy = alarms.copy()
    busy[1:] |= alarms[:-1] & (step[1:] > 0)                      # the step after an alarm (its end)
    if above is not None:
        busy[1:] |= (above[1:] != above[:-1]) & (step[1:] > 0)
        busy |= above & (step == 0)
    tracker = AlertTracker(len(slices), [f for f, _ in slices])
    for j in np.unique(step[busy]):
        act = lengths > j
        rows = np.where(act, first + j, first)     # rows of the flights with a step j (others masked)
        kind = None if types is None else np.asarray(types)[rows]
        tracker.steps[:] = j
        tracker.update(t[rows], scores[rows], alarms[rows] & act, kind,
                       None if above is None else above[rows] & act, active=act)
    tracker.finish()
    done = tracker.closed()
    starts = np.array([first[i] + j for i, j, _ in done], dtype=int)
    return [a for _, _, a in done], starts


def alerts_from_scores(X: pd.DataFrame, scores: np.ndarray, detector=None, *,
                       threshold: float | None = None,
                       typer=None, memo: dict[int, str] | None = None) -> list[Alert]:
    """Alerts of the flights in X (rows grouped by ``flight_id``, time ``t``) for per-step
    ``scores``, under the detector's alarm rule (``score > detector.threshold_``), or under
    ``threshold`` for scores that come without a detector: the ``AlertTracker`` run over them.

    The attack type of an alert is the typer's at its first row when a typer is given (a
    ``ShapeTyper``: ``type_rows``, with ``memo`` shared between calls on the same X), and its
    ``confirmed_type`` the typer's at ``typer.confirm_rows`` (``confirm_s`` later, or the
    flight's last row); else the detector's own classifier's, else ``attack``, unconfirmed."""
    scores = np.asarray(scores, dtype=float)
    if len(scores) != len(X):
        raise ValueError(f"{len(scores)} scores for {len(X)} rows")
    if threshold is None:
        threshold = getattr(detector, "threshold_", None)
        if threshold is None:
            raise ValueError("alerts need an alarm threshold: a calibrated detector or threshold=")
    alarms = scores > threshold
    types = None
    if typer is None and detector is not None and hasattr(detector, "predict_type") and alarms.any():
        types = np.asarray(detector.predict_type(X), dtype=object)
    above = onset_flags(X, detector) if alarms.any() else None
    alerts, starts = track_alerts(X, scores, alarms, types, above)
    if typer is not None and alerts:
        kinds = typer.type_rows(X, starts, memo)
        sure = typer.type_rows(X, typer.confirm_rows(X, starts), memo)
        alerts = [dataclasses.replace(a, attack_type=str(k), confirmed_type=str(c))
                  for a, k, c in zip(alerts, kinds, sure)]
    return alerts


def alerts_frame(alerts: list[Alert]) -> pd.DataFrame:
    return pd.DataFrame([asdict(a) for a in alerts], columns=ALERT_COLUMNS)


def write_alerts(alerts: list[Alert] | pd.DataFrame, path: Path) -> Path:
    """CSV of alerts, written to a temporary sibling and moved into place."""
    frame = alerts if isinstance(alerts, pd.DataFrame) else alerts_frame(alerts)
    with atomic_path(path) as tmp:
        frame.to_csv(tmp, index=False)
    return Path(path)
