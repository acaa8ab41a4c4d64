"""Runs of alarmed steps: what an alarm, an alert and a false-alarm budget count (``alarms``,
``calibration``)."""

from __future__ import annotations

import numpy as np

__all__ = ["runs"]


def runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Half-open [start, end) index runs where ``mask`` is true."""
    m = np.concatenate([[False], np.asarray(mask, dtype=bool), [False]])
    d = np.diff(m.astype(np.int8))
    return list(zip(np.nonzero(d == 1)[0].tolist(), np.nonzero(d == -1)[0].tolist()))
