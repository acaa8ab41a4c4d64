"""One online step: a GPS step's residue row in; score, alarm, GPS admission and alert events out.

The closed loop (``simulation.closed_loop``) and the live monitor (``live.monitor``) drive the
same ``OnlineStep``, as PX4's flight code and its replay call the same ``Ekf::update``; each
driver owns only its clock and its I/O. Per step, for ``n`` flights stepped together:

1. the residue groups become columns (``estimator.schema.as_columns``);
2. the detector's stream scores them (``detector.stream(n)``, or a ``StreamGroup``): score,
   alarm under the detector's rule, its attack types, its onset flags;
3. the admission decides per flight whether the fix is fused (``resilience.admission``), from
   the GPS innovation's NIS and its whitened components in the same row;
4. the alert lifecycle (``detectors.alarms.AlertTracker``) raises, dates (estimated onset),
   types and closes alerts; with an ``OnlineTyper`` (one flight) an alert is raised with the
   shape typer's type at its first row and confirmed ``confirm_s`` later (an ``alert_type``
   event), as ``alerts_from_scores`` types alerts offline;
5. with a ``FlightPhase`` and a ``ReceiverHealth`` (one flight), fed the vehicle's events, the
   receiver's reports and heights between steps (``event``, ``receiver``, ``height``), an alert
   is labelled at its raise with the phase then and its kind: ``degraded`` (the health's reason)
   while the receiver is degraded, else ``spoofing``; an alarm raised as ``degraded`` that still
   stands when the receiver shows a capture sign while the fix moves against the IMU (a capture
   that began with a lost lock) ends there, and a ``spoofing`` alert (reason ``capture: ...``)
   takes it over from that step. The autopilot's own GPS glitch or failsafe report comes after
   the fix it judged: a spoofing alert raised ``GLITCH_LEAD_S`` or less before it, with no
   reason of its own (no capture sign), is relabelled ``degraded`` (``alert_relabel``, its
   ``was_kind`` the kind it had), as one raised a moment later in the episode is. The
   receiver's own spoofing flag raises a spoofing alert (reason ``receiver reports spoofing``)
   without a detector alarm, and its degraded episodes are alerts of their own
   (``OnlineStep.alerts`` holds both, by time).
6. a landing (the ``landed`` or ``disarmed`` event, the height's touchdown, or an impact fed to
   ``impact``: ``detectors.flight_phase``) comes after the alerts raised in the air in its
   ``land_s`` before: the step keeps those alerts and, when the phase declares the landing,
   relabels them ``transition`` with the landing's reason (``alert_relabel`` events, returned by
   the call that fed the landing), so a flight's alerts end with the phases ``phases`` gives.
   The landing explains such an alarm (a hard landing's or a crash's transient), so no attack
   shape is claimed for it: its type, and its confirmed type, become ``unexplained``, as do those
   of the alerts raised in a landing's transition already declared (an impact's hold).

Offline scoring of a whole log (``logs.detect``) computes the same scores in one batch (every
detector's stream equals its ``decision_function``) and runs the same ``AlertTracker`` over
them, so a flight gives the same alerts live and offline.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from quadformer.detectors.alarms import AlertEvent, AlertTracker, with_reason
from quadformer.detectors.attack_types import UNEXPLAINED, OnlineTyper
from quadformer.detectors.flight_phase import FlightPhase
from quadformer.detectors.receiver_health import SPOOFED, ErraticFix, ReceiverHealth
from quadformer.estimator.schema import GROUPS, NIS, as_columns

if TYPE_CHECKING:
    from quadformer.resilience.admission import Decision

GPS_R, GPS_S = GROUPS["res_gps_r"].columns, GROUPS["res_gps_s"].columns   # the admission's inputs
MAX_PENDING = 100          # alerts awaiting their confirmed type (one per alarm start within confirm_s)
#: the fix moving against the IMU, in the raw innovation (not normalised by the receiver's own
#: accuracy, which a capture inflates): a horizontal velocity innovation of this many m/s ...
CAPTURE_SPEED = 1.0
#: ... or a horizontal position innovation of this many m
CAPTURE_JUMP = 3.0
MAX_RECENT = 200           # alerts raised in the air a landing may still relabel
#: an alarm raised at most this long before the autopilot reports a GPS glitch or failsafe was
#: raised on the fixes the autopilot judged (its test and the detector's see the same fix, at
#: most a fix or two apart): it is labelled as if raised in the degraded episode the report opens
GLITCH_LEAD_S = 0.5
GLITCHES = ("gps_glitch", "gps_failsafe")
TRACKER, HEALTH = 0, 1     # who holds an alert the step may relabel


@dataclass(frozen=True)
class StepResult:
    """What one step gives, per flight (arrays of length n)."""
    score: np.ndarray
    alarm: np.ndarray                       # bool
    attack_type: np.ndarray | None          # the type an alert is (or would be) raised with; None: untyped
    columns: dict[str, Any]                 # the residue row as scored
    decision: Decision | None = None        # None without an admission
    state_before: np.ndarray | None = None  # admission states before and after the decision
    state_after: np.ndarray | None = None
    events: list[AlertEvent] = field(default_factory=list)


def _first(cols: Mapping[str, Any], name: str) -> float:
    """The first flight's value of column ``name`` of a row (NaN where the row has none)."""
    return float(np.asarray(cols[name], dtype=float).reshape(-1)[0]) if name in cols else float("nan")


def moving(cols: Mapping[str, Any]) -> str | None:
    """How the fix moves against the IMU in a row's raw GPS innovation (horizontal velocity of at
    least ``CAPTURE_SPEED`` m/s or position of at least ``CAPTURE_JUMP`` m), None when it does
    not or the row has no raw innovation."""
    v = float(np.hypot(_first(cols, "res_gps_r_vx"), _first(cols, "res_gps_r_vy")))
    p = float(np.hypot(_first(cols, "res_gps_r_px"), _first(cols, "res_gps_r_py")))
    if v >= CAPTURE_SPEED:
        return f"the fix moves {v:.1f} m/s against the IMU"
    if p >= CAPTURE_JUMP:
        return f"the fix is {p:.1f} m from the IMU's prediction"
    return None


class OnlineStep:
    """Score, admission and alerts of ``n`` flights, one GPS step at a time (see the module text).

    ``stream``: a detector stream (``detector.stream(n)``, a ``StreamGroup``) or None (scores 0,
    no alarm: policies that need no detector); ``admission``: an ``Admission`` (or group) of the
    same n flights, or None; ``typer``: an ``OnlineTyper`` (one flight only) for shape-typed
    alerts; ``flight_ids``: the names alerts carry; ``keep``: closed alerts kept in memory;
    ``phase``, ``health``: the flight phase and receiver health alerts are labelled by (one
    flight only; the health's ``flight_id`` is the flight's name)."""

    def __init__(self, stream=None, admission=None, *, n: int | None = None,
                 flight_ids: Sequence[Any] | None = None, typer: OnlineTyper | None = None,
                 keep: int | None = None, phase: FlightPhase | None = None,
                 health: ReceiverHealth | None = None):
        sizes = {m for m in (n, getattr(stream, "n", None),
                             len(admission.policies) if admission is not None else None) if m is not None}
        if len(sizes) != 1:
            raise ValueError("OnlineStep: give n, a stream or an admission, all of one batch size "
                             f"(got {sorted(sizes) or 'none'})")
        self.n = sizes.pop()
        if typer is not None and self.n != 1:
            raise ValueError(f"OnlineStep: an OnlineTyper types one flight, not {self.n}")
        if (phase is not None or health is not None) and self.n != 1:
            raise ValueError(f"OnlineStep: a flight phase and a receiver health label one flight, not {self.n}")
        if health is not None:
            if flight_ids is None:
                flight_ids = [health.flight_id]
            elif list(flight_ids) != [health.flight_id]:
                raise ValueError(f"OnlineStep: the receiver health's flight_id {health.flight_id!r} is not "
                                 f"the flight's {list(flight_ids)[0]!r}")
        self.stream, self.admission, self.typer = stream, admission, typer
        self.phase, self.health = phase, health
        self.erratic = ErraticFix()        # a receiver fault's sign in the raw innovation
        self.tracker = AlertTracker(self.n, flight_ids, keep=keep)
        self.pending: deque[tuple[float, str]] = deque(maxlen=MAX_PENDING)
        self.recent: deque[tuple[float, int]] = deque(maxlen=MAX_RECENT)   # (start_s, holder) raised in the air
        self._zeros = np.zeros(self.n)
        self._last_t: float | None = None          # the last step's time (a crash just before the end)
        self._quiet = np.zeros(self.n, dtype=bool)

    def update(self, t, residues: Mapping[str, Any], attacked=None) -> StepResult:
        """One GPS step. ``t``: its time (one value or one per flight); ``residues``: residue groups
        ``{group: (n, width)}`` (as ``ResidueStream`` and the closed loop give them); ``attacked``:
        (n,) which fixes are spoofed (the oracle policy only). Raises ValueError for residues the
        detector cannot score (non-finite): nothing is decided for such a step."""
        return self.update_columns(t, as_columns(residues), attacked)

    def update_columns(self, t, cols: Mapping[str, Any], attacked=None) -> StepResult:
        """``update`` for a residue row already in the flight table's columns ``{column: (n,)}``."""
        self._last_t = float(np.asarray(t, dtype=float).reshape(-1).max())
        if self.stream is not None:
            st = self.stream.update(self._scored(t, cols))
            score, alarm, types, above = st.score, np.asarray(st.alarm, dtype=bool), st.attack_type, st.above
        else:
            score, alarm, types, above = self._zeros, self._quiet, None, None
        dec = before = after = None
        if self.admission is not None:
            before = np.array(self.admission.state)
            nis = np.asarray(cols[NIS], dtype=np.float64)
            r = np.stack([np.asarray(cols[c], dtype=np.float64) for c in GPS_R], axis=-1)
            s = np.stack([np.asarray(cols[c], dtype=np.float64) for c in GPS_S], axis=-1)
            w = r / np.where(s > 0, s, 1.0)
            hit = np.zeros(self.n, dtype=bool) if attacked is None else np.asarray(attacked, dtype=bool)
            dec = self.admission.decide(nis, w, alarm, hit)
            after = np.array(self.admission.state)
        events: list[AlertEvent] = []
        raised, label = alarm, {}
        t0 = float(np.asarray(t).reshape(-1)[0])
        if self.phase is not None or self.health is not None:
            raised, label, events = self._label(t0, alarm, cols)
        kinds = types
        # an alert raised in a landing's transition: the landing explains it, no attack shape
        landing = (self.phase is not None and raised[0] and self.tracker.open[0] is None
                   and label.get("phase") == "transition" and self.phase.reason(t0) is not None)
        if self.typer is not None:
            row = {c: float(np.asarray(v).reshape(-1)[0]) for c, v in cols.items()}
            if self.typer.push(t0, row):
                events += self._confirm(t0)
                if raised[0] and self.tracker.open[0] is None and not landing:
                    kinds = np.array([self.typer.type_now()], dtype=object)
                    self.pending.append((t0, str(kinds[0])))
        if landing:
            kinds = np.full(self.n, UNEXPLAINED, dtype=object)
        a = self.tracker.open[0] if self.health is not None else None
        if a is not None and a.kind == "degraded" and raised[0] and label.get("kind") == "spoofing":
            # an alarm raised while the receiver was degraded (a lost lock) goes on, and now the
            # receiver shows a capture sign while the fix moves against the IMU (or flags spoofing):
            # the degraded alert ends here and a spoofing one takes the alarm over
            ended = self.tracker.end(0, t0)
            events += [] if ended is None else [ended]
        started = self.tracker.update(t, score, raised, kinds, above, **label)
        if self.phase is not None:
            self._watch(started, TRACKER)
        events += started
        if self.typer is not None:          # the open alert's type (raised with the typer's)
            a = self.tracker.open[0]
            kinds = np.array([None if a is None else a.attack_type], dtype=object)
        return StepResult(np.asarray(score, dtype=float), alarm, kinds, cols, dec, before, after, events)

    def _scored(self, t, cols: Mapping[str, Any]) -> Mapping[str, Any]:
        """The row the stream scores: the residue columns with the step's time ``t`` and, with a
        flight phase, ``in_air`` (1 in the air), for the detectors that read them (``glr``)."""
        extra: dict[str, Any] = {}
        if "t" not in cols:
            extra["t"] = np.broadcast_to(np.asarray(t, dtype=float).reshape(-1), (self.n,))
        if self.phase is not None and "in_air" not in cols:
            t0 = float(np.asarray(t).reshape(-1)[0])
            extra["in_air"] = np.array([1.0 if self._phase_at(t0) == "air" else 0.0])
        return {**cols, **extra} if extra else cols

    def _label(self, t: float, alarm: np.ndarray,
               cols: Mapping[str, Any]) -> tuple[np.ndarray, dict[str, Any], list[AlertEvent]]:
        """The alarm the tracker raises on (the detector's, or the receiver's spoofing flag), what
        a new alert is labelled with, and the receiver's episodes the step's time closes.

        A capture sign of the receiver (its satellites, noise, jamming or accuracy jumping:
        ``ReceiverHealth.capture_sign``) while the fix moves against the IMU (``moving``) makes an
        alarm ``spoofing``, reason ``capture: ...``, whatever else the receiver says (a capture may
        lose the lock for a moment), unless the fix is erratic (``receiver_health.ErraticFix``: its
        velocity against the IMU swinging both ways, a receiver fault), which makes it
        ``degraded``; otherwise a degraded receiver (a lost or missed fix, an accuracy jump, the
        autopilot's glitch or failsafe) makes it ``degraded``."""
        label: dict[str, Any] = {"phase": self._phase_at(t)}
        landing = None if self.phase is None else self.phase.reason(t)
        if landing is not None:
            label["reason"] = landing
        events = []
        if self.health is not None:
            events = self.health.tick(t)
            why = self.health.degraded(t)
            sign = self.health.capture_sign(t)
            move = moving(cols) if sign is not None else None
            self.erratic.push(t, _first(cols, "res_gps_r_vx"), _first(cols, "res_gps_r_vy"))
            fault = self.erratic.reason(t)
            if self.health.spoof_flag(t):
                alarm = np.ones(1, dtype=bool)
                label.update(kind="spoofing", reason=with_reason(SPOOFED, landing))
            elif fault is not None:
                label.update(kind="degraded", reason=with_reason(fault, landing))
            elif move is not None:
                label.update(kind="spoofing", reason=with_reason(f"capture: {sign}; {move}", landing))
            elif why is not None:
                label.update(kind="degraded", reason=with_reason(why, landing))
        return alarm, label, events

    def _phase_at(self, t: float) -> str:
        return "air" if self.phase is None else self.phase.update(t)

    def _health_label(self, t: float) -> dict[str, Any]:
        """What a degraded episode opened at t is labelled with: the phase, and a landing's reason."""
        if self.phase is None:
            return {"phase": "air"}
        return {"phase": self.phase.update(t), "phase_reason": self.phase.reason(t)}

    def event(self, t: float, kind: str) -> list[AlertEvent]:
        """One of the vehicle's events at t (``flight_phase.VEHICLE_EVENTS``,
        ``receiver_health.GPS_EVENTS``; others are ignored) fed to the phase and the health;
        returns the events of the degraded episodes it opens or closes and of the alerts a
        landing it declares relabels."""
        events = []
        if self.phase is not None:
            self.phase.event(t, kind)
            events = self._landed()
        if self.health is not None:
            events += self._glitched(t, kind)
            opened = self.health.event(t, kind, **self._health_label(t))
            self._watch(opened, HEALTH)
            events += opened
        return events

    def _glitched(self, t: float, kind: str) -> list[AlertEvent]:
        """The open spoofing alert raised within ``GLITCH_LEAD_S`` before the autopilot's GPS glitch
        or failsafe at t relabelled ``degraded``, as an alarm raised a moment later, in the episode,
        is (its event). Not one with a reason (a capture's, the receiver's own spoofing flag, a
        landing's): a capture stays spoofing whatever the autopilot calls its jump."""
        a = self.tracker.open[0]
        if (kind not in GLITCHES or a is None or a.kind != "spoofing" or a.reason is not None
                or not t - GLITCH_LEAD_S <= a.start_s <= t):
            return []
        why = f"autopilot GPS {kind.removeprefix('gps_')} {t - a.start_s:.2f} s after its raise"
        ev = self.tracker.relabel(0, a.start_s, a.phase, why, t, kind="degraded")
        return [] if ev is None else [ev]

    def receiver(self, t: float, **report) -> list[AlertEvent]:
        """One status report of the receiver at t (``ReceiverHealth.report``'s fields) fed to the
        health; returns the events of the degraded episodes it opens or closes."""
        if self.health is None:
            return []
        events = self.health.report(t, **report, **self._health_label(t))
        self._watch(events, HEALTH)
        return events

    def height(self, t: float, h: float) -> list[AlertEvent]:
        """A height sample at t (m, any datum) fed to the flight phase; returns the events of the
        alerts a landing it declares (the height's touchdown) relabels."""
        if self.phase is None:
            return []
        self.phase.update(t, h)
        return self._landed()

    def impact(self, t: float, crash: bool = False, how: str = "impact") -> list[AlertEvent]:
        """An impact at t (``detectors.impact``: ``crash``, ``how`` in words) fed to the flight
        phase; returns the events of the alerts it relabels where it counts as a landing."""
        if self.phase is None:
            return []
        self.phase.impact(t, crash, how)
        return self._landed()

    def _watch(self, events: list[AlertEvent], holder: int) -> None:
        """Keep the alerts raised in the air among ``events`` for a landing to relabel (and forget
        those no landing can reach any more)."""
        if self.phase is None:
            return
        for ev in events:
            if ev.event == "alert_start" and ev.alert.phase == "air":
                self.recent.append((ev.alert.start_s, holder))
                self._forget(ev.alert.start_s)

    def _forget(self, t: float) -> None:
        """Drop the alerts raised before the earliest landing not yet declared at t can reach."""
        horizon = self.phase.touchdown(t) - self.phase.rule.land_s
        while self.recent and self.recent[0][0] < horizon:
            self.recent.popleft()

    def _landed(self) -> list[AlertEvent]:
        """The alerts raised in the air within ``land_s`` before each landing the phase declared
        since the last call, up to when it was seen, relabelled ``transition`` (their events); the
        alerts no landing can reach any more forgotten."""
        events = []
        land_s = self.phase.rule.land_s
        for landing in self.phase.pop_landings():
            kept = deque(maxlen=MAX_RECENT)
            for start, holder in self.recent:
                if landing.t - land_s <= start < landing.seen_t:
                    if holder == TRACKER:       # the landing explains it: its type is confirmed no more
                        self.pending = deque((p for p in self.pending if p[0] != start), maxlen=MAX_PENDING)
                    ev = (self.tracker.relabel(0, start, "transition", landing.reason, landing.seen_t,
                                               attack_type=UNEXPLAINED)
                          if holder == TRACKER else
                          self.health.relabel(start, "transition", landing.reason, landing.seen_t))
                    if ev is not None:
                        events.append(ev)
                else:
                    kept.append((start, holder))
            self.recent = kept
            self._forget(landing.seen_t)
        return events

    def _confirm(self, t: float | None) -> list[AlertEvent]:
        """Confirm the types of alerts raised ``confirm_s`` or more before t (all at the end, t None)."""
        out = []
        while self.pending and (t is None or t >= self.pending[0][0] + self.typer.typer.confirm_s):
            start, raised = self.pending.popleft()
            ev = self.tracker.confirm(0, start, self.typer.type_now(), self.typer.last_t)
            if ev is not None:
                out.append(AlertEvent(ev.event, ev.flight, ev.t, ev.alert, ev.step, raised_as=raised))
        return out

    def open_alert(self, i: int = 0):
        """Flight i's open alert, with its peak score so far (None when none is open)."""
        a = self.tracker.open[i]
        if a is None:
            return None
        return replace(a, score=self.tracker.peak(i))

    def finish(self) -> list[AlertEvent]:
        """The end of the data: a crash just before it declared a landing, open alerts closed
        (``end_s`` None), then pending types confirmed."""
        events = []
        if self.phase is not None and self._last_t is not None:
            self.phase.finish(self._last_t)
            events += self._landed()
        events += self.tracker.finish()
        if self.typer is not None and self.typer.history:
            events += self._confirm(None)
        if self.health is not None:
            events += self.health.finish()
        return events

    @property
    def alerts(self):
        """The closed alerts kept, by flight and time (the receiver's degraded episodes among them)."""
        alerts = [a for _, _, a in self.tracker.closed()]
        if self.health is not None:
            alerts = sorted(alerts + self.health.alerts, key=lambda a: a.start_s)
        return alerts
