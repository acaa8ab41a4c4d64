"""What the live monitor reports: its state in words, the periodic status line (with the flight
phase, and the receiver's degradation while it lasts), the summary (``summary.json``: the alerts
counted apart by kind and flight phase as ``detect`` counts a log's, the headline the spoofing
alerts in the air) and the summary text printed at the end, read from the monitor's counters;
and the fixed-size latency histogram those report per fix."""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Protocol

import numpy as np

from quadformer.io import package_versions
from quadformer.live.intake import STREAMS, Intake
from quadformer.resilience.admission import BLENDING, EXCLUDED, FUSING

__all__ = ["STALE", "STATES", "Latency", "SegmentState", "state_text", "status_line", "summary", "summary_text"]

STATES = {FUSING: "fusing", EXCLUDED: "GPS excluded", BLENDING: "re-admitting GPS"}


class SegmentState(Protocol):
    """What the state in words reads of the monitor's current segment (``live.segment``)."""
    fixes: int          # fixes scored in the segment
    state: int          # the GPS admission state (``resilience.admission``)
STALE = "stale"                   # the state while the IMU or GPS the filter needs is silent


class Latency:
    """Fixed-size log-spaced histogram (1 us to 10 s, about 2.3% per bin): percentiles over a
    whole run without keeping the samples."""

    LO, PER_DECADE, DECADES = -6.0, 100, 7

    def __init__(self):
        self.counts = np.zeros(self.PER_DECADE * self.DECADES + 1, dtype=np.int64)
        self.n, self.max = 0, 0.0

    def add(self, seconds: float) -> None:
        i = int((math.log10(max(seconds, 1e-6)) - self.LO) * self.PER_DECADE)
        self.counts[min(max(i, 0), len(self.counts) - 1)] += 1
        self.n += 1
        self.max = max(self.max, seconds)

    def quantile(self, q: float) -> float:
        if self.n == 0:
            return math.nan
        i = int(np.searchsorted(np.cumsum(self.counts), q * self.n))
        return 10 ** (self.LO + (i + 0.5) / self.PER_DECADE)


def state_text(intake: Intake, seg: SegmentState | None) -> str:
    """waiting for IMU, stale (the IMU or GPS silent longer than ``stale_s``), waiting for
    fix, or the admission state."""
    if "imu" not in intake.last_t:
        return "waiting for IMU"
    if intake.silent():
        return STALE
    if seg is None or seg.fixes == 0:
        return "waiting for fix"
    return STATES[seg.state]


def status_line(m: Any, elapsed: float = 1.0) -> str:
    """One line of the monitor ``m`` (``live.monitor.Monitor``, read, not imported: it reports
    through this module): time, segment, stream rates over ``elapsed`` s, fixes, score, state,
    silent streams and the link's losses."""
    intake = m.intake
    rates = " ".join(f"{s} {intake.window[s] / max(elapsed, 1e-9):.0f}" for s in STREAMS if s in intake.last_t)
    seg = m.segment
    score = f"{seg.last_score:.3g}" if seg is not None and math.isfinite(seg.last_score) else "-"
    now = f"t {intake.now_t:.1f} s (boot {intake.time.boot(intake.now_t):.1f} s)" \
        if math.isfinite(intake.now_t) else "t -"
    parts = [now, f"seg {seg.index if seg else '-'}", f"{rates or 'no samples'} /s", f"fixes {m.fixes}",
             f"score {score} (thr {m.detector.threshold_:.3g})", m.state_text()]
    if math.isfinite(intake.now_t):
        parts.append(f"phase {m.flight.phase.update(intake.now_t)}")
        why = seg.step.health.degraded(intake.now_t) if seg is not None and seg.step.health is not None else None
        if why is not None:
            parts.append(f"receiver degraded: {why}")
    need = ["imu", "gps"] + [s for s in ("mag", "baro", "vio") if s in m.sensors.split("+")]
    for s in need:
        age = intake.stale(s)
        if age > m.config.stale_s:
            parts.append(f"no {s.upper()} for {age:.0f} s")
    packets = intake.packets
    late = sum(v for k, v in m.dropped.items() if k.endswith(("_late", "_duplicate")))
    parts.append(f"packets lost {packets['lost']} bad {m.messages['BAD_DATA']} dup {packets['duplicate']} "
                 f"reord {packets['reordered']}")
    parts.append(f"samples late/dup {late}")
    return " | ".join(parts)


def summary(m: Any, wall_s: float) -> dict[str, Any]:
    """The summary of the monitor ``m`` (``live.monitor.Monitor``) after ``wall_s`` seconds of its
    clock (``summary.json``)."""
    dropped = dict(sorted(m.dropped.items()))
    intake, packets = m.intake, m.intake.packets
    return {
        "stop_reason": m.stop_reason, "wall_s": wall_s,
        "config": m.config.to_dict(), "filter": dataclasses.asdict(m.filter_config),
        "gps_delay": {"s": m.filter_config.gps_delay_s, "source": m.latency_source},
        "gps_epochs": {"restamped": m.receiver_epochs.restamped, "jitter_ms": m.receiver_epochs.jitter * 1e3,
                       "hold_ms": m.receiver_epochs.allowance * 1e3,
                       "largest_hold_ms": m.receiver_epochs.largest_allowance * 1e3,
                       "restarts": m.receiver_epochs.restarts,
                       "note": m.receiver_epochs.note()},
        "sensors": m.sensors,
        "detector": {"name": m.detector.name, "model": m.model, "threshold": float(m.detector.threshold_),
                     "features": list(m.detector.features_)},
        "vehicle": {"system": m.vehicle, "autopilot": m.autopilot, "imu": intake.imu_source,
                    "baro": intake.baro_source, "gps_receiver": intake.gps_instance,
                    "origin": m.origin, "origin_source": m.origin_source},
        "state": m.state_text(),
        "time": {"t": "s since the link's first sensor sample", "boot_t": "s since the vehicle's boot",
                 **intake.summary()},
        "rates_hz": dict(intake.rates),
        "messages": dict(sorted(m.messages.items())), "n_messages": m.n_messages,
        "messages_per_s": m.n_messages / wall_s if wall_s > 0 else math.nan,
        "samples": dict(intake.samples), "fixes_scored": m.fixes, **m.alert_counts,
        "alert_list": [dataclasses.asdict(a) for a in m.alerts],
        "flight": {"phase": m.flight.phase.update(intake.now_t) if math.isfinite(intake.now_t) else None,
                   **m.flight.summary()},
        "link": {"lost_packets": packets["lost"], "corrupt_packets": m.messages["BAD_DATA"],
                 "duplicate_packets": packets["duplicate"], "reordered_packets": packets["reordered"],
                 "datagrams": intake.reader.datagrams if intake.reader is not None else None,
                 "duplicates": sum(v for k, v in dropped.items() if k.endswith("_duplicate")),
                 "late": sum(v for k, v in dropped.items() if k.endswith("_late")),
                 "dropped": dropped, "stream_gaps": intake.gaps},
        "segments": m.n_segments, "segment_list": list(m.segments),
        "errors": m.errors, "last_error": m.last_error,
        "latency_ms": {"p50": m.latency.quantile(0.5) * 1e3, "p99": m.latency.quantile(0.99) * 1e3,
                       "max": m.latency.max * 1e3, "n": m.latency.n},
        "actions": dict(m.link.counts) if m.link is not None else {},
        "vehicle_source_set": m.link.source_set if m.link is not None else None,
        "notes": list(m.notes), "versions": package_versions(),
    }


def summary_text(s: dict[str, Any]) -> str:
    """The summary (``summary``'s dict) in a few lines for the console."""
    link = s["link"]
    msgs = ", ".join(f"{k} {v}" for k, v in sorted(s["messages"].items(), key=lambda kv: -kv[1])[:12])
    return "\n".join([
        f"monitor stopped ({s['stop_reason']}) after {s['wall_s']:.1f} s: {s['n_messages']} messages "
        f"({s['messages_per_s']:.0f}/s)",
        f"  messages: {msgs or 'none'}",
        f"  fixes scored {s['fixes_scored']}, spoofing alerts in the air {s['alerts']} (beside them "
        f"{s['alerts_ground']} on the ground, {s['alerts_transition']} in a take-off or landing transition, "
        f"{s['alerts_degraded']} of a degraded receiver), segments {s['segments']}, errors {s['errors']}",
        f"  state at the end: {s['state']}; t counts from the link's first sensor sample, at "
        + (f"{s['time']['first_sample_boot_s']:.3f} s after the vehicle's boot"
           if s["time"]["first_sample_boot_s"] is not None else "none received"),
        f"  link: packets lost {link['lost_packets']}, corrupt {link['corrupt_packets']}, "
        f"duplicate packets {link['duplicate_packets']}, reordered {link['reordered_packets']}; "
        f"samples duplicate {link['duplicates']}, late {link['late']}; other drops "
        + (", ".join(f"{k} {v}" for k, v in link["dropped"].items()
                     if not k.endswith(("_duplicate", "_late"))) or "none"),
        f"  latency per fix (message in hand to admission decision): p50 {s['latency_ms']['p50']:.2f} ms, "
        f"p99 {s['latency_ms']['p99']:.2f} ms",
    ])
