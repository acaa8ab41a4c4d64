"""The detector contract shared by every method (scikit-learn / pyod style).

- ``__init__`` stores keyword arguments only.
- ``fit(X, y=None)`` learns from training flights and returns self; ``y`` (labels per
  step, -1 where unknown) is optional, for methods that use labels.
- ``decision_function(X)`` returns one score per row, higher meaning more anomalous. It is
  causal: the score of a step uses that flight's steps up to it only.
- ``calibrate(X_val)`` chooses the alarm rule (``score > threshold_``) on validation flights
  (best F1, or a false-alarm budget: ``detectors.calibration``) and returns self;
  ``calibrate(threshold)`` sets one chosen elsewhere. The rule is learned state, saved and
  loaded with the detector, so a saved model alone reproduces its alarms. ``predict`` gives 0/1.
- ``get_params`` / ``set_params`` follow scikit-learn (``set_params`` changes the detector in
  place and returns it), so ``sklearn.base.clone`` gives an unfitted copy.
- ``stream(n_flights)`` scores n flights online, one GPS step at a time, with the same
  scores and alarms as ``decision_function`` (see ``detectors.streams``).
- ``features_`` (learned) names the residue columns the detector reads.

``X`` is a DataFrame of GPS steps with ``flight_id``, ``t`` and the ``res_*`` residues,
rows grouped by flight and ordered in time (as in a dataset's ``flights.parquet``).
"""

from __future__ import annotations

import copy
import inspect
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pandas as pd

from quadformer.detectors.calibration import CRITERIA, choose_thresholds, gps_rate
from quadformer.io import write_json


class NotFittedError(RuntimeError):
    """A detector used before ``fit``."""


class Detector:
    name: ClassVar[str] = "detector"
    #: hyper-parameter grid searched on validation flights (same rule for every method)
    param_grid: ClassVar[dict[str, list[Any]]] = {}

    # -- parameters -------------------------------------------------------------------
    def get_params(self, deep: bool = True) -> dict[str, Any]:
        """The constructor arguments, by name. ``deep`` is accepted for scikit-learn; no
        detector holds another estimator as a parameter, so it changes nothing."""
        sig = inspect.signature(type(self).__init__)
        out = {k: getattr(self, k) for k in sig.parameters if k not in ("self", "params", "kwargs")}
        return out

    def set_params(self, **params: Any) -> "Detector":
        """Set constructor arguments in place (scikit-learn semantics); returns self. Learned
        state is left as it is: refit for the new parameters to take effect."""
        valid = self.get_params()
        unknown = sorted(set(params) - set(valid))
        if unknown:
            raise ValueError(f"{self.name}: invalid parameter(s) {', '.join(unknown)}; "
                             f"valid: {', '.join(sorted(valid))}")
        for k, v in params.items():
            setattr(self, k, v)
        return self

    #: post-processing parameters (e.g. an alarm rule) tuned without refitting
    post_grid: ClassVar[dict[str, list[Any]]] = {}

    def with_post(self, **post: Any) -> "Detector":
        """A shallow copy sharing the fitted state, with post-processing parameters changed."""
        other = copy.copy(self)
        for k, v in post.items():
            setattr(other, k, v)
        return other

    # -- contract ---------------------------------------------------------------------
    def fit(self, X: pd.DataFrame, y: np.ndarray | None = None) -> "Detector":
        raise NotImplementedError

    def decision_function(self, X: pd.DataFrame) -> np.ndarray:
        raise NotImplementedError

    def stream(self, n_flights: int = 1):
        """Online scoring of ``n_flights`` flights stepped together (``detectors.streams``)."""
        raise NotImplementedError

    # -- alarm rule -------------------------------------------------------------------
    def calibrate(self, X: pd.DataFrame | float, y: np.ndarray | float | None = None, *, criterion: str = "f1",
                  budget_per_hour: float = 1.0, gps_rate_hz: float | None = None,
                  scores: np.ndarray | None = None, budget_threshold: float | None = None,
                  **provenance: Any) -> "Detector":
        """Set the alarm rule, ``score > threshold_``, on validation flights; returns self.

        ``calibrate(X_val, y_val=None)``: choose it on validation flights ``X_val`` (labels
        ``y_val``, 1 on attacked steps; default: the ``label`` column). ``threshold_`` is the
        threshold of best point-wise F1 (``criterion="f1"``) or the one meeting the false-alarm
        budget (``criterion="budget"``); ``budget_threshold_`` is always the latter: at most
        ``budget_per_hour`` alarm runs per flight-hour on the clean validation flights (those
        without an attacked step; every flight when there are no labels), ``gps_rate_hz`` steps
        per second (default: from the ``t`` column). ``scores``: ``decision_function(X_val)``
        if already computed.

        ``calibrate(threshold, budget_threshold=None)`` (the latter also by keyword): set a rule
        chosen elsewhere.

        ``provenance`` (e.g. the split seed and test flights) is kept with the rule."""
        self.check_fitted()
        if isinstance(X, pd.DataFrame):
            if budget_threshold is not None:
                raise TypeError(f"{self.name}: the budget threshold is chosen on the validation flights; "
                                "set budget_per_hour instead")
            threshold, budget = self._choose(X, y, criterion, budget_per_hour, gps_rate_hz, scores)
        else:
            if scores is not None or gps_rate_hz is not None or criterion != "f1" or budget_per_hour != 1.0:
                raise TypeError(f"{self.name}: criterion, budget_per_hour, gps_rate_hz and scores choose a "
                                "threshold on validation flights; pass the flights (a DataFrame), not a number")
            if y is not None and budget_threshold is not None:
                raise TypeError(f"{self.name}: the budget threshold given twice")
            threshold, budget = X, (y if budget_threshold is None else budget_threshold)
        if not np.isfinite(threshold):
            raise ValueError(f"{self.name}: threshold must be finite, got {threshold!r}")
        self.threshold_ = float(threshold)
        self.budget_threshold_ = None if budget is None else float(budget)
        if provenance:
            self.calibration_ = dict(provenance)
        return self

    def _choose(self, X: pd.DataFrame, y: np.ndarray | None, criterion: str, budget_per_hour: float,
                gps_rate_hz: float | None, scores: np.ndarray | None) -> tuple[float, float]:
        """(threshold, budget threshold) chosen on validation flights ``X``."""
        if criterion not in CRITERIA:
            raise ValueError(f"{self.name}: criterion must be one of {', '.join(CRITERIA)}, got {criterion!r}")
        if y is None and "label" in X.columns:
            y = X["label"].to_numpy()
        if y is None:
            if criterion == "f1":
                raise ValueError(f"{self.name}: the F1 criterion needs labels: pass y or a 'label' column "
                                 "(or criterion='budget' on clean flights)")
            y = np.zeros(len(X), dtype=np.int8)
        y = np.asarray(y)
        if y.shape != (len(X),) or not np.isin(y, (0, 1)).all():
            raise ValueError(f"{self.name}: validation labels must be 0 or 1, one per row of X")
        s = self.decision_function(X) if scores is None else np.asarray(scores, float)
        if s.shape != (len(X),):
            raise ValueError(f"{self.name}: {s.size} scores for {len(X)} validation rows")
        rate = gps_rate(X) if gps_rate_hz is None else gps_rate_hz
        thr = choose_thresholds(s, y, X["flight_id"].to_numpy(), rate, budget_per_hour)
        if criterion == "f1":
            return thr.f1, thr.budget
        if not np.isfinite(thr.budget):
            raise ValueError(f"{self.name}: no clean validation flight to meet the false-alarm budget on")
        return thr.budget, thr.budget

    def at_budget(self) -> "Detector":
        """A shallow copy whose alarm threshold is the false-alarm-budget one."""
        if getattr(self, "budget_threshold_", None) is None:
            raise NotFittedError(f"{self.name}: no false-alarm-budget threshold; calibrate it first")
        return self.with_post(threshold_=self.budget_threshold_)

    def predict(self, X: pd.DataFrame) -> np.ndarray:
        self.check_fitted()
        if getattr(self, "threshold_", None) is None:
            raise NotFittedError(f"{self.name}: no threshold; call calibrate() on validation flights first")
        return (self.decision_function(X) > self.threshold_).astype(np.int8)

    def check_fitted(self) -> None:
        """Raise ``NotFittedError`` unless ``fit`` (or ``load``) has run."""
        if not getattr(self, "fitted_", False):
            raise NotFittedError(f"{self.name}: call fit() before scoring")

    # -- persistence ------------------------------------------------------------------
    def learned_state(self) -> dict[str, Any]:
        """Learned attributes (ending in ``_``) as JSON-ready values."""
        out = {}
        for k, v in vars(self).items():
            if k.endswith("_") and not k.startswith("_"):
                out[k] = v.tolist() if isinstance(v, np.ndarray) else v
        return out

    def load_state(self, state: dict[str, Any]) -> None:
        """Restore what ``learned_state`` returned."""
        for k, v in state.items():
            setattr(self, k, np.asarray(v) if isinstance(v, list) else v)

    def save(self, path: str | Path) -> Path:
        """JSON with the method name, parameters and learned state, alarm rule included
        (written atomically, after any file ``save_extra`` writes beside it)."""
        path = Path(path)
        doc = {"method": self.name, "params": self.saved_params(), "state": self.learned_state(),
               "format_version": 1}
        self.save_extra(path)
        write_json(path, doc)
        return path

    def saved_params(self) -> dict[str, Any]:
        """Hook: the parameters the saved document records (default: ``get_params``)."""
        return self.get_params()

    def save_extra(self, path: Path) -> None:
        """Hook: files saved beside the JSON document (e.g. network weights)."""

    def load_extra(self, path: Path) -> None:
        """Hook: read what ``save_extra`` wrote."""


def flight_slices(X: pd.DataFrame) -> list[tuple[Any, np.ndarray]]:
    """(flight_id, row indices) per flight, in order of appearance."""
    fid = X["flight_id"].to_numpy()
    if fid.size == 0:
        return []
    change = np.nonzero(np.diff(fid))[0] + 1
    starts = np.concatenate([[0], change])
    ends = np.concatenate([change, [fid.size]])
    seen = fid[starts]
    if len(set(seen.tolist())) != len(seen):
        raise ValueError("rows of each flight must be contiguous (group rows by flight_id)")
    return [(seen[i], np.arange(starts[i], ends[i])) for i in range(len(starts))]


def check_residues(X: pd.DataFrame, columns: list[str]) -> np.ndarray:
    """The residue columns as floats; a clear error for missing columns or non-finite values."""
    missing = [c for c in ["flight_id", *columns] if c not in X.columns]
    if missing:
        raise ValueError(f"missing columns: {', '.join(missing)}")
    arr = X[columns].to_numpy(dtype=float)
    bad = ~np.isfinite(arr)
    if bad.any():
        row, col = np.argwhere(bad)[0]
        raise ValueError(f"non-finite residue in column {columns[col]} at row {row} "
                         f"(flight {X['flight_id'].iloc[row]}); drop or repair such steps first")
    return arr


def labelled_split(X: pd.DataFrame, y: np.ndarray | None, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Row indices (train, held-out) of the labelled flights, split by flight."""
    if y is None:
        raise ValueError("this detector needs labels: pass y (label per step, -1 where unknown)")
    y = np.asarray(y)
    fids = [f for f, idx in flight_slices(X) if np.all(y[idx] >= 0)]
    if not fids:
        raise ValueError("no labelled training flight: raise the label fraction")
    rng = np.random.default_rng(seed)
    fids = list(rng.permutation(fids))
    n_hold = max(1, len(fids) // 5) if len(fids) >= 3 else 0
    hold = set(fids[:n_hold])
    fid = X["flight_id"].to_numpy()
    lab = y >= 0
    return np.nonzero(lab & ~np.isin(fid, list(hold)))[0], np.nonzero(lab & np.isin(fid, list(hold)))[0]
