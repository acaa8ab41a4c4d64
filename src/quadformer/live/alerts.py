"""What the live monitor says and does about its decisions: the online step's alert events
(``resilience.step.OnlineStep``: start, end, confirmed type, relabelled phase) and the admission's transitions
(GPS excluded, re-admitted) become console lines, STATUSTEXTs to the vehicle, records in
``alerts.jsonl``, ``on_alert`` calls and, with ``act``, the EKF source set switch. The last
``MAX_ALERTS`` ended alerts are kept for the summary (all are in ``alerts.jsonl``), and every
alert raised is counted by kind and flight phase (``detectors.alert_counts``: the headline, the
spoofing alerts in the air, and the others beside it). An alert raised in the air shortly before
a landing is relabelled when the landing is seen (``alert_relabel``: a console line and a record
in ``alerts.jsonl``, nothing to the vehicle): the alerts kept and the counts take its new phase,
and the alerts kept its type (``unexplained``: the landing explains it).

Each alert says its kind (``spoofing``, or ``degraded``: raised while the receiver was degraded,
or the receiver's degraded episode itself), its flight phase and its reason. Its STATUSTEXT
(``statustext``) is at most 50 characters: ``GPS SPOOF ALERT <type> s=<score>`` (severity ALERT)
with ``on ground``, ``in takeoff`` or ``in landing`` outside the air and ``GPS excluded`` when the
alert excluded GPS, or ``GPS DEGRADED: <reason>`` (severity WARNING, the reason's words before
its parenthesis, e.g. ``fix lost``) with ``alarm <type>`` for a detector alarm raised then; what
does not fit is left out, the score first."""

from __future__ import annotations

import dataclasses
import math
from collections import Counter, deque
from datetime import datetime, timezone
from typing import Callable

from quadformer.detectors.alarms import Alert, alert_counts, phase_words
from quadformer.live.actions import STATUSTEXT_MAX, Records, VehicleLink
from quadformer.live.config import MonitorConfig
from quadformer.live.status import STATES
from quadformer.sensors.mavlink import mavlink2
from quadformer.resilience.admission import BLENDING, EXCLUDE_NIS, EXCLUDED, READMIT_STALE

__all__ = ["MAX_ALERTS", "Alerting", "describe", "statustext"]

MAX_ALERTS = 1000                 # alerts kept in memory (all are in alerts.jsonl)
SHORT_PHASE = {"ground": "on ground", "transition": "in takeoff"}     # STATUSTEXT words (none in the air)


def episode(a: Alert) -> bool:
    """Whether an alert is the receiver's degraded episode itself (no detector score)."""
    return a.kind == "degraded" and not math.isfinite(a.score)


def describe(a: Alert) -> str:
    """An alert's kind, reason and flight phase in words: "spoofing in the air", "degraded
    receiver (fix lost (fix type 1)) on the ground"."""
    what = "spoofing" if a.kind == "spoofing" else "degraded receiver"
    why = f" ({a.reason})" if a.reason else ""
    return f"{what}{why} {phase_words(a.phase, a.reason)}"


def short_phase(a: Alert) -> str | None:
    """An alert's flight phase in a STATUSTEXT's words (None in the air)."""
    if phase_words(a.phase, a.reason) == "in the landing transition":
        return "in landing"
    return SHORT_PHASE.get(a.phase)


def statustext(a: Alert, score: float, exclusion: bool = False) -> str:
    """The STATUSTEXT of an alert's start (see the module text), at most ``STATUSTEXT_MAX``
    characters; ``exclusion``: GPS was excluded at this alert's fix."""
    where = short_phase(a)
    excluded = "GPS excluded" if exclusion else None
    if a.kind == "degraded":
        head = f"GPS DEGRADED: {(a.reason or 'receiver').split('; ')[0].split(' (')[0]}"
        alarm = None if episode(a) else f"alarm {a.attack_type}"
        parts = [(alarm, 2), (where, 1), (excluded, 3)]          # (text, the order they are left out in, last first)
    else:
        head = f"GPS SPOOF ALERT {a.attack_type}"
        parts = [(f"s={score:.3g}" if math.isfinite(score) else None, 3), (where, 1), (excluded, 2)]
    parts = [p for p in parts if p[0]]
    text = " ".join([head, *(p for p, _ in parts)])
    while len(text) > STATUSTEXT_MAX and parts:
        parts.remove(max(parts, key=lambda p: p[1]))
        text = " ".join([head, *(p for p, _ in parts)])
    return text[:STATUSTEXT_MAX]


class Alerting:
    """The alert and admission side of the monitor: ``echo`` every console line, ``on_alert``
    every alert event; ``attach`` gives it the vehicle link and the records once the
    connection is open (before that, console and callbacks only). ``alerts``: the ended
    alerts kept, ``n_alerts``: alerts raised, ``counts``: they counted apart by kind and flight
    phase (``detectors.alert_counts``)."""

    def __init__(self, detector, config: MonitorConfig, echo: Callable[[str], None],
                 on_alert: Callable[[dict], None] | None = None):
        self.detector, self.config, self.echo, self.on_alert = detector, config, echo, on_alert
        self.link: VehicleLink | None = None
        self.records: Records | None = None
        self.alerts: deque[Alert] = deque(maxlen=MAX_ALERTS)
        self.n_alerts = 0
        self.counts: Counter = Counter(alert_counts([]))

    def attach(self, link: VehicleLink | None, records: Records | None) -> None:
        self.link, self.records = link, records

    def admission(self, t: float, before: int, after: int, readmit: int = 0, exclude: int = 0,
                  held: float | None = None) -> None:
        """The admission messages and actions of one fix; ``readmit`` / ``exclude``: the rule
        that acted at this fix (``Decision.readmit`` / ``Decision.exclude``), ``held``: the hold a
        re-admission waited for (``Decision.held``; longer than the setting after repeated alarms)."""
        c = self.config
        if after == EXCLUDED and before != EXCLUDED:
            if exclude == EXCLUDE_NIS:
                self.echo(f"[t {t:.1f} s] GPS excluded (fix outside the agreement gate under the standing alarm)")
                if self.link is not None:
                    self.link.statustext("GPS excluded: fix disagrees, alert standing", mavlink2.MAV_SEVERITY_ALERT)
            else:
                self.echo(f"[t {t:.1f} s] GPS excluded (detector alarm)")
            if c.act and self.link is not None:
                self.link.set_source(c.act_source_set)
                self.echo(f"[t {t:.1f} s] act: EKF source set {c.act_source_set} (non-GPS) requested")
        elif after == BLENDING and before == EXCLUDED:
            if readmit == READMIT_STALE:
                self.echo(f"[t {t:.1f} s] GPS re-admitted (agreeing for {held or c.admission.stale_hold_s:g} s "
                          "despite a standing alarm)")
                if self.link is not None:
                    self.link.statustext("GPS re-admitted: fixes agree, alert stale", mavlink2.MAV_SEVERITY_NOTICE)
            else:
                self.echo(f"[t {t:.1f} s] GPS re-admitted (clear and agreeing for {held or c.admission.hold_s:g} s)")
                if self.link is not None:
                    self.link.statustext("GPS re-admitted: spoof alert cleared", mavlink2.MAV_SEVERITY_NOTICE)
            if c.act and self.link is not None:
                self.link.set_source(1)
                self.echo(f"[t {t:.1f} s] act: EKF source set 1 (GPS) requested")

    def events(self, events: list, segment: int, score: float, state: int, exclusion: bool = False) -> None:
        """The online step's alert events of one segment: counted, kept, written, sent and
        echoed. ``score``: the segment's last score (an alert start's), ``state``: the
        admission state after the fix, ``exclusion``: GPS was excluded at this fix."""
        for ev in events:
            a = ev.alert
            now = datetime.now(timezone.utc)
            event = {"event": ev.event, "segment": segment, "vehicle_t": ev.t,
                     "wall_time": now.isoformat(timespec="milliseconds"), "unix_time": now.timestamp()}
            if ev.event == "alert_type":
                event.update(start_s=a.start_s, attack_type=a.confirmed_type, raised_as=ev.raised_as)
                self._amend(a, confirmed_type=a.confirmed_type)
                kind, raised = a.confirmed_type, ev.raised_as
                self.echo(f"[t {ev.t:.1f} s] alert of t {a.start_s:.1f} s: type {kind}"
                          + (f" (raised as {raised})" if kind != raised else " confirmed"))
            elif ev.event == "alert_relabel":
                event.update(start_s=a.start_s, kind=a.kind, attack_type=a.attack_type, phase=a.phase, was=ev.was,
                             was_kind=ev.was_kind, reason=a.reason)
                self._amend(a, kind=a.kind, phase=a.phase, reason=a.reason, attack_type=a.attack_type,
                            confirmed_type=a.confirmed_type)
                self.counts.subtract(alert_counts([dataclasses.replace(a, phase=ev.was, kind=ev.was_kind or a.kind)]))
                self.counts.update(alert_counts([a]))
                if ev.was_kind is not None:
                    self.echo(f"[t {ev.t:.1f} s] alert of t {a.start_s:.1f} s: {a.kind}, not {ev.was_kind} "
                              f"({a.reason})")
                else:
                    self.echo(f"[t {ev.t:.1f} s] alert of t {a.start_s:.1f} s: {phase_words(a.phase, a.reason)}, "
                              f"not {phase_words(ev.was)} ({a.reason})")
            else:
                value = a.score if ev.event == "alert_end" or episode(a) else float(score)
                event.update(score=value if math.isfinite(value) else None, onset_s=a.onset_s,
                             attack_type=a.attack_type, kind=a.kind, phase=a.phase, reason=a.reason,
                             admission=STATES[state], threshold=float(self.detector.threshold_))
                if ev.event == "alert_start":
                    self._raised(a, value, exclusion)
                else:
                    self.alerts.append(a)
                    event.update(start_s=a.start_s, peak_score=event["score"])
                self.echo(self._line(ev, value, segment, state))
            if self.records is not None:
                self.records.alert(event)
            if self.on_alert is not None:
                self.on_alert(event)

    def _amend(self, a: Alert, **changes) -> None:
        """The kept alert of ``a``'s flight and start, changed."""
        self.alerts = deque((dataclasses.replace(b, **changes) if b.flight_id == a.flight_id and b.start_s == a.start_s
                             else b for b in self.alerts), maxlen=MAX_ALERTS)

    def _raised(self, a: Alert, score: float, exclusion: bool) -> None:
        """An alert raised: counted, and told to the vehicle."""
        self.n_alerts += 1
        self.counts.update(alert_counts([a]))
        if self.link is not None:
            severity = mavlink2.MAV_SEVERITY_WARNING if a.kind == "degraded" else mavlink2.MAV_SEVERITY_ALERT
            self.link.statustext(statustext(a, score, exclusion), severity)

    def _line(self, ev, score: float, segment: int, state: int) -> str:
        """The console line of an alert's start or end."""
        a = ev.alert
        when = f"t {ev.t:.1f} s" if ev.t is not None else "end of segment"
        tail = f"segment {segment}, {STATES[state]}"
        if episode(a):
            what = "GPS DEGRADED" if ev.event == "alert_start" else "GPS degraded episode ended"
            return f"[{when}] {what}: {a.reason}, {phase_words(a.phase, a.reason)}, {tail}"
        what = "ALERT" if ev.event == "alert_start" else "alert ended"
        return (f"[{when}] {what}: {a.attack_type}, score {score:.3g} (threshold {self.detector.threshold_:.3g}), "
                f"{describe(a)}, {tail}")
