"""What the live monitor says and does about its decisions: the online step's alert events
(``resilience.step.OnlineStep``: start, end, confirmed type) and the admission's transitions
(GPS excluded, re-admitted) become console lines, STATUSTEXTs to the vehicle, records in
``alerts.jsonl``, ``on_alert`` calls and, with ``act``, the EKF source set switch. The last
``MAX_ALERTS`` ended alerts are kept for the summary (all are in ``alerts.jsonl``)."""

from __future__ import annotations

import dataclasses
from collections import deque
from datetime import datetime, timezone
from typing import Callable

from quadformer.detectors.alarms import Alert
from quadformer.live.actions import Records, VehicleLink
from quadformer.live.config import MonitorConfig
from quadformer.live.status import STATES
from quadformer.sensors.mavlink import mavlink2
from quadformer.resilience.admission import BLENDING, EXCLUDE_NIS, EXCLUDED, READMIT_STALE

__all__ = ["MAX_ALERTS", "Alerting"]

MAX_ALERTS = 1000                 # alerts kept in memory (all are in alerts.jsonl)


class Alerting:
    """The alert and admission side of the monitor: ``echo`` every console line, ``on_alert``
    every alert event; ``attach`` gives it the vehicle link and the records once the
    connection is open (before that, console and callbacks only). ``alerts``: the ended
    alerts kept, ``n_alerts``: alerts raised."""

    def __init__(self, detector, config: MonitorConfig, echo: Callable[[str], None],
                 on_alert: Callable[[dict], None] | None = None):
        self.detector, self.config, self.echo, self.on_alert = detector, config, echo, on_alert
        self.link: VehicleLink | None = None
        self.records: Records | None = None
        self.alerts: deque[Alert] = deque(maxlen=MAX_ALERTS)
        self.n_alerts = 0

    def attach(self, link: VehicleLink | None, records: Records | None) -> None:
        self.link, self.records = link, records

    def admission(self, t: float, before: int, after: int, readmit: int = 0, exclude: int = 0) -> None:
        """The admission messages and actions of one fix; ``readmit`` / ``exclude``: the rule
        that acted at this fix (``Decision.readmit`` / ``Decision.exclude``)."""
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
                self.echo(f"[t {t:.1f} s] GPS re-admitted (agreeing for {c.admission.stale_hold_s:g} s "
                          "despite a standing alarm)")
                if self.link is not None:
                    self.link.statustext("GPS re-admitted: fixes agree, alert stale", mavlink2.MAV_SEVERITY_NOTICE)
            else:
                self.echo(f"[t {t:.1f} s] GPS re-admitted (clear and agreeing for {c.admission.hold_s:g} s)")
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
                self.alerts = deque((dataclasses.replace(b, confirmed_type=a.confirmed_type)
                                     if b.flight_id == a.flight_id and b.start_s == a.start_s else b
                                     for b in self.alerts), maxlen=MAX_ALERTS)
                kind, raised = a.confirmed_type, ev.raised_as
                self.echo(f"[t {ev.t:.1f} s] alert of t {a.start_s:.1f} s: type {kind}"
                          + (f" (raised as {raised})" if kind != raised else " confirmed"))
            else:
                value = a.score if ev.event == "alert_end" else float(score)
                event.update(score=value, onset_s=a.onset_s, attack_type=a.attack_type, admission=STATES[state],
                             threshold=float(self.detector.threshold_))
                if ev.event == "alert_start":
                    self.n_alerts += 1
                    text = f"GPS SPOOF ALERT {a.attack_type} s={value:.3g}"
                    if exclusion:
                        text += " GPS excluded"
                    if self.link is not None:
                        self.link.statustext(text, mavlink2.MAV_SEVERITY_ALERT)
                else:
                    self.alerts.append(a)
                    event.update(start_s=a.start_s, peak_score=a.score)
                when = f"t {ev.t:.1f} s" if ev.t is not None else "end of segment"
                self.echo(f"[{when}] {'ALERT' if ev.event == 'alert_start' else 'alert ended'}: {a.attack_type}, "
                          f"score {value:.3g} (threshold {self.detector.threshold_:.3g}), segment {segment}, "
                          f"{STATES[state]}")
            if self.records is not None:
                self.records.alert(event)
            if self.on_alert is not None:
                self.on_alert(event)
