"""Any registered detector, online over a batch of flights stepped together.

``OnlineScorer.update(residues)`` takes this GPS step's residue columns for every flight
and returns each flight's score and alarm, equal to what the detector's offline
``decision_function`` gives at that step (every detector is causal). Detectors with a
batched stream (QUADFormer) use it; the others are scored on the latest
``context_steps`` steps of each flight (the whole flight for recursive statistics).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from quadformer.detectors.base import Detector


class OnlineScorer:
    def __init__(self, detector: Detector, n_flights: int, threshold: float | None = None):
        detector._check_fitted()
        self.det = detector
        self.n = n_flights
        self.threshold = getattr(detector, "threshold_", None) if threshold is None else threshold
        if self.threshold is None:
            raise ValueError(f"{detector.name}: no alarm threshold (tune or calibrate it first)")
        self.features = list(getattr(detector, "features_", None) or [])
        self._stream = detector.batch_stream(n_flights) if hasattr(detector, "batch_stream") else None
        self._context = detector.context_steps
        self._rows: list[dict[str, np.ndarray]] = []
        self.step = 0

    def update(self, residues: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """residues: column name -> (n_flights,) values of this step. Returns (scores, alarms)."""
        if self._stream is not None:
            missing = [c for c in self.features if c not in residues]
            if missing:
                raise KeyError(f"{self.det.name}: residue column {missing[0]!r} missing")
            x = np.stack([np.asarray(residues[c], dtype=float) for c in self.features], axis=1)
            score = self._stream.update(x)[0]
        else:
            self._rows.append({k: np.asarray(v, dtype=float) for k, v in residues.items()})
            if self._context is not None and len(self._rows) > self._context:
                self._rows.pop(0)
            L = len(self._rows)
            frame = {"flight_id": np.repeat(np.arange(self.n), L),
                     "t": np.tile(np.arange(self.step - L + 1, self.step + 1, dtype=float), self.n)}
            for k in self._rows[0]:
                frame[k] = np.stack([r[k] for r in self._rows], axis=1).reshape(-1)   # flight-major
            s = self.det.decision_function(pd.DataFrame(frame))
            score = s.reshape(self.n, L)[:, -1]
        self.step += 1
        return score, score > self.threshold
