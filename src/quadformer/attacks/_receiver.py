"""A receiver's status reports under an attack: what a captured receiver says of itself.

``spoofed_reports(frame, attack, t0)`` takes a frame of receiver reports (a column ``t`` and any
of ``fix_type``, ``satellites``, ``eph``, ``epv``, ``speed_acc``, ``noise``: a flight log's
``receiver`` or ``gps`` stream) and the one-flight ``AttackBatch`` injected into it, whose times
count from ``t0`` on the frame's clock, and returns a new frame with the attack's effects
(``AttackBatch.receiver_effects``) applied: satellites and noise scaled and rounded, accuracies
scaled, the fix type 1 while the lock is lost. A value the receiver does not report (NaN) stays
NaN, except the fix type, which is 1 while the lock is lost. Attacks other than a capture leave
the frame's values as they are.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from quadformer.attacks._attacks import AttackBatch

#: the report columns an attack changes, and whether they are counts (rounded)
REPORT_COLUMNS = {"satellites": True, "eph": False, "epv": False, "speed_acc": False, "noise": True}
NO_FIX = 1.0        # the fix type of a receiver without a fix (PX4 and MAVLink: 0-1 no fix)


def spoofed_reports(frame: pd.DataFrame, attack: AttackBatch, t0: float = 0.0) -> pd.DataFrame:
    """``frame`` (receiver reports with a column ``t``) with the effects of ``attack`` (one flight,
    its times from ``t0`` on the frame's clock) applied; a new frame, ``frame`` is left alone."""
    if len(attack.kind) != 1:
        raise ValueError(f"spoofed_reports takes the AttackBatch of one flight, got {len(attack.kind)} flights")
    if "t" not in frame.columns:
        raise ValueError(f"spoofed_reports needs a column t (s), got columns {list(frame.columns)}")
    out = frame.copy()
    fx = attack.receiver_effects(frame["t"].to_numpy(dtype=float) - float(t0))
    for col, count in REPORT_COLUMNS.items():
        if col in out.columns:
            v = out[col].to_numpy(dtype=float) * fx[col][:, 0]
            out[col] = np.round(v) if count else v
    if "fix_type" in out.columns:
        lost = fx["fix_lost"][:, 0]
        out["fix_type"] = np.where(lost, NO_FIX, out["fix_type"].to_numpy(dtype=float))
    return out
