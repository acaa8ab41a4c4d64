"""Alarm runs and alert events: a detector's alarms as an operator or an autopilot sees them.

One alert per run of consecutive alarmed steps of a flight: when it was raised, the
estimated onset of the attack (from the detector's onset criterion where it has one, else
the alarm time), its attack type (from a typer such as ``attack_types.ShapeTyper`` where
one is given, else from the detector where it classifies, else ``attack``), the peak score
during the run and when the run ended (``None`` while still alarmed at the end of the data).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from quadformer.detectors.base import flight_slices
from quadformer.io import atomic_path

ALERT_COLUMNS = ["flight_id", "start_s", "onset_s", "attack_type", "score", "end_s", "confirmed_type"]


def runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Half-open [start, end) index runs where ``mask`` is true."""
    m = np.concatenate([[False], np.asarray(mask, dtype=bool), [False]])
    d = np.diff(m.astype(np.int8))
    return list(zip(np.nonzero(d == 1)[0].tolist(), np.nonzero(d == -1)[0].tolist()))


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

    def __str__(self) -> str:
        end = f"{self.end_s:.1f} s" if self.end_s is not None else "open"
        confirmed = f", confirmed {self.confirmed_type}" if self.confirmed_type is not None else ""
        return (f"flight {self.flight_id}: {self.attack_type} alert at {self.start_s:.1f} s "
                f"(onset ~{self.onset_s:.1f} s, until {end}, peak score {self.score:.3g}{confirmed})")


def alerts_from_scores(X: pd.DataFrame, scores: np.ndarray, detector=None, *,
                       threshold: float | None = None,
                       typer=None, memo: dict[int, str] | None = None) -> list[Alert]:
    """Alerts of the flights in X (rows grouped by ``flight_id``, time ``t``) for per-step
    ``scores``, under the detector's alarm rule (``score > detector.threshold_``), or under
    ``threshold`` for scores that come without a detector.

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
    onsets: dict[tuple[Any, float], float] = {}
    if detector is not None and hasattr(detector, "onset_times"):
        onsets = {(fid, ta): to for fid, ta, to in detector.onset_times(X, alarms)}
    t = X["t"].to_numpy(dtype=float)
    found = [(fid, idx, s, e) for fid, idx in flight_slices(X) for s, e in runs(alarms[idx])]
    starts = np.array([idx[s] for _, idx, s, _ in found], dtype=int)
    confirmed = np.full(len(found), None, dtype=object)
    if typer is not None:
        types = typer.type_rows(X, starts, memo)
        confirmed = typer.type_rows(X, typer.confirm_rows(X, starts), memo)
    elif detector is not None and hasattr(detector, "predict_type"):
        types = detector.predict_type(X)[starts]
    else:
        types = np.full(len(found), "attack", dtype=object)
    out = []
    for (fid, idx, s, e), kind, sure in zip(found, types, confirmed):
        t0 = float(t[idx[s]])
        out.append(Alert(
            flight_id=fid.item() if hasattr(fid, "item") else fid, start_s=t0,
            onset_s=float(onsets.get((fid, t0), t0)),
            attack_type=str(kind),
            score=float(scores[idx[s:e]].max()),
            end_s=float(t[idx[e]]) if e < len(idx) else None,
            confirmed_type=None if sure is None else str(sure)))
    return out


def alerts_frame(alerts: list[Alert]) -> pd.DataFrame:
    return pd.DataFrame([asdict(a) for a in alerts], columns=ALERT_COLUMNS)


def write_alerts(alerts: list[Alert] | pd.DataFrame, path: Path) -> Path:
    """CSV of alerts, written to a temporary sibling and moved into place."""
    frame = alerts if isinstance(alerts, pd.DataFrame) else alerts_frame(alerts)
    with atomic_path(path) as tmp:
        frame.to_csv(tmp, index=False)
    return Path(path)
