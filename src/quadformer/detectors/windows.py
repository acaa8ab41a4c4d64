"""Causal windows over residue sequences and per-feature normalisation.

The window of step k of a flight holds that flight's steps k-W+1 .. k (padded before the
flight starts with the inputs' ``pad``: zero for normalised residues, zero being the training
median after normalisation; the median itself for raw residues fed to a scorer that
normalises them, such as an exported graph), so a score computed from it uses data up to k
only. Windows are views into one padded array: nothing is copied until a batch is gathered.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from quadformer.detectors.base import check_residues, flight_slices
from quadformer.detectors.streams import DetectorStream, RingBuffer
from quadformer.estimator.schema import DETECTOR_FEATURES, axis_columns



def input_features(X) -> list[str]:
    """The default detector inputs (``estimator.schema.DETECTOR_FEATURES``) present in X;
    datasets written before the correction integral existed simply lack it."""
    return [c for c in DETECTOR_FEATURES if c in X.columns]


class Normalizer:
    """Per-feature robust centring and scaling (median, IQR), then asinh compression.

    Residues are heavy-tailed (an attack multiplies the NIS by tens to thousands); asinh keeps
    them ordered without letting a few steps dominate training. Fitted on training rows only.
    """

    #: a step before the flight starts, in normalised space (the training median)
    pad = 0.0

    def fit(self, values: np.ndarray) -> "Normalizer":
        self.mean_ = np.median(values, axis=0)
        q75, q25 = np.percentile(values, [75, 25], axis=0)
        std = (q75 - q25) / 1.349
        self.std_ = np.where(std > 1e-12, std, 1.0)
        return self

    def transform(self, values: np.ndarray) -> np.ndarray:
        return np.arcsinh((values - self.mean_) / self.std_).astype(np.float32)

    def state(self) -> dict:
        return {"mean": self.mean_.tolist(), "std": self.std_.tolist()}

    @classmethod
    def from_state(cls, state: dict) -> "Normalizer":
        n = cls()
        n.mean_ = np.asarray(state["mean"], dtype=float)
        n.std_ = np.asarray(state["std"], dtype=float)
        return n

    def raw(self) -> "RawInputs":
        """The inputs of a scorer that applies this normalisation itself."""
        return RawInputs(self.mean_)


class RawInputs:
    """Raw residues as float32 windows, for a scorer that normalises them itself (an exported
    graph). Padded with the normaliser's centre, which normalisation maps to exactly zero
    (the float32 centre minus itself), so windows match the normalised ones, padding included.
    """

    def __init__(self, centre: np.ndarray):
        self.pad = np.asarray(centre, dtype=np.float32)

    def transform(self, values: np.ndarray) -> np.ndarray:
        return np.asarray(values, dtype=np.float32)


class Windows:
    """All causal windows of the rows of X: ``windows[idx]`` -> (len(idx), W, features).
    ``normalizer`` maps residues to window values and gives the padding: a ``Normalizer``, or
    ``RawInputs`` for raw residues."""

    def __init__(self, X: pd.DataFrame, features: list[str], normalizer: Normalizer | RawInputs, width: int):
        values = normalizer.transform(check_residues(X, features))
        d = values.shape[1]
        parts, rows, ends = [], [], np.empty(len(X), dtype=np.int64)
        offset = 0
        for _, idx in flight_slices(X):
            parts.append(np.full((width - 1, d), normalizer.pad, dtype=np.float32))
            parts.append(values[idx])
            rows += [np.full(width - 1, -1), idx]
            offset += width - 1
            ends[idx] = offset + np.arange(len(idx))
            offset += len(idx)
        self._data = np.concatenate(parts) if parts else np.zeros((0, d), dtype=np.float32)
        self._rows = np.concatenate(rows) if rows else np.zeros(0, dtype=np.int64)
        self._start = ends - (width - 1)
        self.width = width

    def __len__(self) -> int:
        return len(self._start)

    def _offsets(self, idx: np.ndarray) -> np.ndarray:
        return self._start[np.asarray(idx)][:, None] + np.arange(self.width)[None, :]

    def __getitem__(self, idx: np.ndarray) -> np.ndarray:
        return self._data[self._offsets(idx)]

    def tokens(self, idx: np.ndarray, context) -> np.ndarray:
        """``context.tokens(self[idx])`` (a ``detectors.context.Context`` of this width) without
        gathering whole windows: the mean of every ``patch`` consecutive rows is computed once
        (the same float64 sum and float32 rounding as ``Context.tokens``), and each window
        takes its patch means and its last ``fine`` rows from it. Offline scoring of long
        windows reads a sixth of the data this way."""
        if context.window != self.width:
            raise ValueError(f"a context of {context.window} steps for windows of {self.width}")
        idx = np.asarray(idx)
        start = self._start[idx]
        split = context.n_patches * context.patch
        fine = self._data[start[:, None] + split + np.arange(context.fine)[None, :]]
        if not context.n_patches:
            return fine
        means = self.__dict__.get("_patch_means")
        if means is None or means[0] != context.patch:
            view = np.lib.stride_tricks.sliding_window_view(self._data, context.patch, axis=0)
            means = (context.patch, view.mean(axis=-1, dtype=np.float64).astype(np.float32))
            self._patch_means = means
        coarse = means[1][start[:, None] + context.patch * np.arange(context.n_patches)[None, :]]
        return np.concatenate([coarse, fine], axis=1)

    def spans(self, idx: np.ndarray, max_rows: int):
        """The windows idx in chunks that each cover a short run of rows: ``(positions in idx,
        rows (S, features), starts)`` per chunk, window ``idx[positions[i]]`` being
        ``rows[starts[i]:starts[i] + width]``. Windows are taken in the order of their first
        row; a chunk covers at most ``max(max_rows, width)`` rows (a view, nothing copied), so a
        scorer that works on every row of a chunk (per-step projections) works on each row about
        once when the windows are dense, and never on the whole data at once."""
        idx = np.asarray(idx)
        first = self._start[idx]
        order = np.argsort(first, kind="stable")
        first = first[order]
        reach = max(int(max_rows) - self.width, 0)
        i = 0
        while i < len(order):
            lo = first[i]
            j = max(int(np.searchsorted(first, lo + reach, side="right")), i + 1)
            yield order[i:j], self._data[lo:first[j - 1] + self.width], first[i:j] - lo
            i = j

    def gather(self, idx: np.ndarray, fn) -> np.ndarray:
        """``fn(windows)`` of the windows idx, concatenated: gathered a chunk at a time, so long
        windows never sit in memory all at once (e.g. ``fn = context.tokens``)."""
        idx = np.asarray(idx)
        step = chunk_size(self.width, self._data.shape[1])
        parts = [fn(self[idx[i:i + step]]) for i in range(0, len(idx), step)]
        return np.concatenate(parts) if parts else fn(self[idx[:0]])

    def rows(self, idx: np.ndarray) -> np.ndarray:
        """Row indices of X in each window (len(idx), W); -1 for the padding."""
        return self._rows[self._offsets(idx)]


CHUNK_BYTES = 32 << 20   # windows gathered per scoring call: about this many bytes


def chunk_size(window: int, n_features: int) -> int:
    """Windows per scoring call: ``CHUNK_BYTES`` of float32 windows, between 64 and 4096."""
    return int(np.clip(CHUNK_BYTES // (4 * window * max(1, n_features)), 64, 4096))


def window_scores(detector, X: pd.DataFrame) -> np.ndarray:
    """Score of every row of X by a window detector: its ``score_windows`` over the causal
    windows of its features (``features_``, ``normalizer_``, ``window``), a chunk at a time.
    A detector that reads only its windows' tokens (``score_tokens``) is given them directly
    (``Windows.tokens``): the same scores, without gathering whole windows."""
    win = Windows(X, detector.features_, detector.normalizer_, detector.window)
    out = np.empty(len(win), dtype=np.float64)
    by_tokens = hasattr(detector, "score_tokens")
    step = chunk_size(detector.context.n_tokens if by_tokens else detector.window, len(detector.features_))
    for i in range(0, len(win), step):
        idx = np.arange(i, min(i + step, len(win)))
        out[idx] = (detector.score_tokens(win.tokens(idx, detector.context)) if by_tokens
                    else detector.score_windows(win[idx]))[0]
    return out


class AxisSymmetry:
    """Training augmentation: a spoof's direction is random, so a detector should not care
    which way an innovation points. Each training window gets a random sign per axis (applied
    to the GPS position/velocity innovations, raw and whitened, the VIO velocity innovation
    of that axis and, for z, the barometric height innovation) and a random swap of the two
    horizontal axes. Normalised features are centred (median 0) and asinh is odd, so a sign
    flip there is one in the data.
    """

    def __init__(self, features: list[str]):
        pos = {c: i for i, c in enumerate(features)}
        self.axes = []
        for a in "xyz":
            self.axes.append([pos[n] for n in axis_columns(a) if n in pos])
        self.perm = np.arange(len(features))
        for i, j in zip(self.axes[0], self.axes[1]):
            self.perm[i], self.perm[j] = j, i

    def __call__(self, xb, rng: np.random.Generator):
        import torch

        n = xb.shape[0]
        sign = torch.ones(n, 1, xb.shape[-1], dtype=xb.dtype)
        flips = torch.from_numpy(rng.choice([-1.0, 1.0], size=(n, 3)).astype(np.float32))
        for a, idx in enumerate(self.axes):
            if idx:
                sign[:, 0, idx] = flips[:, a:a + 1]
        xb = xb * sign
        swap = torch.from_numpy(rng.random(n) < 0.5)
        if swap.any():
            xb[swap] = xb[swap][..., torch.from_numpy(self.perm)]
        return xb


class WindowStream(DetectorStream):
    """A window detector online: a ring buffer of the last ``window`` normalised residues
    per flight (padded before the first step, as offline), scored by the detector's
    ``score_windows(windows (n, W, features)) -> (scores (n,), attack types (n,) or None)``,
    the function its offline ``decision_function`` applies to every window. ``inputs``: what
    the detector's windows hold (default its ``normalizer_``; ``RawInputs`` for raw residues)."""

    def __init__(self, detector, n_flights: int, inputs: Normalizer | RawInputs | None = None):
        super().__init__(detector, n_flights)
        self.inputs = detector.normalizer_ if inputs is None else inputs
        self.buf = RingBuffer(self.n, detector.window, len(self.features), fill=self.inputs.pad)

    def _score(self, x):
        windows = self.buf.push(self.inputs.transform(x))
        return self.detector.score_windows(windows)
