"""One streaming contract for every detector: ``detector.stream(n_flights)``.

``stream.update(residues)`` takes one GPS step of ``n_flights`` flights stepped together,
either a mapping ``column -> (n,) values`` (extra columns are ignored) or an array
``(n, len(features_))`` in the order of the detector's ``features_`` (``(features,)`` when
n is 1), and returns a ``StreamStep``: each flight's score, its alarm under the detector's
alarm rule (``score > threshold_``; no alarm before ``calibrate``) and, for detectors that
classify attacks, the predicted attack type. A stream's scores and alarms equal the
detector's offline ``decision_function`` on the same flights (every detector is causal):
exactly for the recursive statistics, to float32 rounding for the networks.

State is bounded: a recursion's state, or ring buffers of the last steps a window needs;
no history grows. The closed loop, and any live loop, drive the same objects.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class StreamStep:
    score: np.ndarray                   # (n,) higher = more anomalous
    alarm: np.ndarray                   # (n,) bool
    attack_type: np.ndarray | None      # (n,) predicted type names (classifiers), else None
    above: np.ndarray | None = None     # (n,) bool, raw score above the onset level (detectors with an
                                        # onset criterion: ``AlertTracker`` dates an alert's onset by it)


class DetectorStream:
    """Input checking and the alarm rule; subclasses implement ``_score`` (and those of detectors
    with an onset criterion set ``above``, the onset flags of the last step)."""

    above: np.ndarray | None = None

    def __init__(self, detector, n_flights: int):
        detector.check_fitted()
        if not (isinstance(n_flights, (int, np.integer)) and n_flights >= 1):
            raise ValueError(f"n_flights must be an integer >= 1, got {n_flights!r}")
        self.detector = detector
        self.n = int(n_flights)
        self.features = list(detector.features_)

    def _matrix(self, residues) -> np.ndarray:
        n, d = self.n, len(self.features)
        if isinstance(residues, Mapping):
            missing = [c for c in self.features if c not in residues]
            if missing:
                raise ValueError(f"{self.detector.name}: residue column {missing[0]!r} missing "
                                 f"(needs {', '.join(self.features)})")
            x = np.stack([np.broadcast_to(np.asarray(residues[c], dtype=float), (n,)) for c in self.features],
                         axis=1)
        else:
            x = np.asarray(residues, dtype=float)
            if n == 1 and x.ndim == 1:
                x = x[None]
        if x.shape != (n, d) or not np.isfinite(x).all():
            raise ValueError(f"{self.detector.name}: residues must be {n} row(s) of {d} finite values "
                             f"({', '.join(self.features)})")
        return x

    def update(self, residues) -> StreamStep:
        score, types = self._score(self._matrix(residues))
        thr = getattr(self.detector, "threshold_", None)
        alarm = score > thr if thr is not None else np.zeros(self.n, dtype=bool)
        return StreamStep(score, alarm, types, self.above)

    def _score(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        raise NotImplementedError


class RingBuffer:
    """The last ``length`` rows of each of ``n`` flights, oldest first, filled with ``fill``
    (one value, or one per column) before the first push (padded windows, as offline)."""

    def __init__(self, n: int, length: int, width: int | None = None, fill: float | np.ndarray = 0.0,
                 dtype: type = np.float32):
        shape = (n, length) if width is None else (n, length, width)
        self.data = np.full(shape, fill, dtype=dtype)

    def push(self, rows: np.ndarray) -> np.ndarray:
        self.data[:, :-1] = self.data[:, 1:]
        self.data[:, -1] = rows
        return self.data


class StreamGroup:
    """Several detectors' streams side by side over one batch of flights: ``streams`` cover
    consecutive slices of the batch (the first ``streams[0].n`` flights, then the next, ...),
    each driven by its own detector (flights of different configurations flown together, each
    configuration with the detector tuned on it). ``update`` gives each stream its slice and
    joins their steps; a slice's scores and alarms are those of its stream alone."""

    def __init__(self, streams: list[DetectorStream]):
        if not streams:
            raise ValueError("StreamGroup: at least one stream needed")
        self.streams = list(streams)
        self.n = sum(s.n for s in self.streams)
        self._bounds = np.cumsum([0] + [s.n for s in self.streams])

    def update(self, residues) -> StreamStep:
        steps = []
        for s, a, b in zip(self.streams, self._bounds[:-1], self._bounds[1:]):
            if isinstance(residues, Mapping):
                part = {c: (np.asarray(v)[a:b] if np.ndim(v) else v) for c, v in residues.items()}
            else:
                part = np.asarray(residues)[a:b]
            steps.append(s.update(part))
        types = None
        if any(st.attack_type is not None for st in steps):
            types = np.concatenate([st.attack_type if st.attack_type is not None
                                    else np.full(len(st.score), None, dtype=object) for st in steps])
        above = None
        if any(st.above is not None for st in steps):
            above = np.concatenate([st.above if st.above is not None else np.zeros(len(st.score), dtype=bool)
                                    for st in steps])
        return StreamStep(np.concatenate([st.score for st in steps]),
                          np.concatenate([st.alarm for st in steps]), types, above)


class ScoredStream:
    """The stream of steps scored beforehand, for one flight: ``update`` gives row k of
    ``score``, ``alarm``, ``attack_type`` and ``above`` at its k-th call (the residues passed are
    not read). Offline replay scores a whole log in one batch, which equals the detector's own
    stream row by row (see the module text), and drives the online step with this one."""

    n = 1

    def __init__(self, score: np.ndarray, alarm: np.ndarray, attack_type: np.ndarray | None = None,
                 above: np.ndarray | None = None):
        self.score = np.asarray(score, dtype=float)
        self.alarm = np.asarray(alarm, dtype=bool)
        self.attack_type = None if attack_type is None else np.asarray(attack_type, dtype=object)
        self.above = None if above is None else np.asarray(above, dtype=bool)
        sizes = {len(a) for a in (self.score, self.alarm, self.attack_type, self.above) if a is not None}
        if len(sizes) != 1:
            raise ValueError(f"ScoredStream: score, alarm, attack_type and above differ in length ({sorted(sizes)})")
        self.k = 0

    def update(self, residues=None) -> StreamStep:
        k = self.k
        if k >= len(self.score):
            raise IndexError(f"ScoredStream: all {len(self.score)} steps given")
        self.k += 1
        cut = slice(k, k + 1)
        return StreamStep(self.score[cut], self.alarm[cut],
                          None if self.attack_type is None else self.attack_type[cut],
                          None if self.above is None else self.above[cut])
