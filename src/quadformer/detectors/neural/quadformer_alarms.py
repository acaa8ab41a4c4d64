"""QUADFormer's alarm rule and onset criterion, offline and online, on numpy alone (an exported
graph scored with onnxruntime uses them without torch): an alarm where at least k of a flight's
last n raw scores exceed the threshold (``kth_of_last_n`` offline, ``KofN`` online), an alert's
onset back-tracked to where the raw score last rose above a level (``onset_times``), and the two
streams that feed the rule: over whole windows (``KofNStream``) and one step at a time
(``StepStream``)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from quadformer.detectors.alarms import runs
from quadformer.detectors.base import flight_slices
from quadformer.detectors.context import StepTokens
from quadformer.detectors.streams import DetectorStream, RingBuffer
from quadformer.detectors.windows import Normalizer, RawInputs, WindowStream

__all__ = ["FLOOR", "KofN", "KofNStream", "StepStream", "kth_of_last_n", "onset_times"]


def onset_times(X: pd.DataFrame, alarms: np.ndarray, raw: np.ndarray, lower: float
                ) -> list[tuple[Any, float, float]]:
    """(flight, alarm time, estimated onset time) for each alarm run: back from the alarm to
    where the raw score last rose above ``lower``."""
    t = X["t"].to_numpy()
    out = []
    for fid, idx in flight_slices(X):
        for s, _ in runs(np.asarray(alarms)[idx]):
            j = s
            while j > 0 and raw[idx[j - 1]] > lower:
                j -= 1
            out.append((fid, float(t[idx[s]]), float(t[idx[j]])))
    return out


FLOOR = -1e6   # score before k steps of a flight exist (never alarms)


def kth_of_last_n(raw: np.ndarray, X: pd.DataFrame, k: int, n: int) -> np.ndarray:
    """Per flight, the k-th largest of the last n raw scores (``FLOOR`` while fewer than k
    steps of the flight exist)."""
    out = np.full(len(raw), FLOOR)
    for _, idx in flight_slices(X):
        r = raw[idx]
        pad = np.r_[np.full(n - 1, FLOOR), r]
        view = np.lib.stride_tricks.sliding_window_view(pad, n)        # (len, n)
        out[idx] = np.sort(view, axis=1)[:, n - k]
    return out


class KofN:
    """The k-of-n rule online: a ring buffer of the last n raw scores of each flight (``FLOOR``
    before the flight's start); ``push(raw)`` -> the k-th largest of them, the decision."""

    def __init__(self, n_flights: int, k: int, n: int):
        self.k, self.n = int(k), int(n)
        self.last = RingBuffer(n_flights, self.n, fill=FLOOR, dtype=np.float64)

    def push(self, raw: np.ndarray) -> np.ndarray:
        return np.sort(self.last.push(raw), axis=1)[:, self.n - self.k]


class KofNStream(WindowStream):
    """QUADFormer online over whole windows: the window stream's raw scores and types, then the
    k-of-n rule (``KofN``). Any detector with ``window``, ``k``, ``n`` and ``score_windows`` (raw
    scores, types): an exported graph of whole windows (``detectors.export``)."""

    def __init__(self, detector, n_flights: int, inputs: Normalizer | RawInputs | None = None):
        super().__init__(detector, n_flights, inputs)
        self.rule = KofN(self.n, detector.k, detector.n)
        self.onset_level = getattr(detector, "onset_level_", None)

    def _score(self, x):
        raw, types = super()._score(x)
        if self.onset_level is not None:
            self.above = raw > self.onset_level
        return self.rule.push(raw), types


class StepStream(DetectorStream):
    """QUADFormer online, one step at a time (``quadformer_steps``): the state per flight is the
    window's step embeddings (``context.StepTokens``, zero before the flight's start, as the
    padding); each step, ``score_step(inputs (n, features), context (n, T-1, width))`` gives the
    raw scores, attack types and the new steps' embeddings, which join the state; then the
    k-of-n rule (``KofN``). ``score_step`` is the detector's own (PyTorch) or an exported
    streaming graph's (onnxruntime, ``detectors.export``); ``inputs`` maps residues to its
    inputs (the normaliser, or ``RawInputs`` for a graph that normalises). The detector gives
    ``context``, ``k``, ``n`` and ``onset_level_``."""

    def __init__(self, detector, n_flights: int, score_step, inputs: Normalizer | RawInputs, width: int):
        super().__init__(detector, n_flights)
        self.score_step = score_step
        self.inputs = inputs
        self.tokens = StepTokens(detector.context, self.n, width)
        self.rule = KofN(self.n, detector.k, detector.n)
        self.onset_level = getattr(detector, "onset_level_", None)

    def _score(self, x):
        raw, types, embedding = self.score_step(self.inputs.transform(x), self.tokens.context())
        self.tokens.push(embedding)
        if self.onset_level is not None:
            self.above = raw > self.onset_level
        return self.rule.push(raw), types
