"""The evaluation protocol, identical for every method.

1. Flights are split train / validation / test (60/20/20) by flight, fixed by the seed and
   stratified by whether the flight is attacked.
2. Learning methods see the labels of a fraction of the training flights (default 20%);
   the other training steps carry label -1 (unknown). Classical methods may use the same.
3. For every point of a method's hyper-parameter grid: fit on train, score validation,
   take the threshold that maximises validation F1. The grid point with the best validation
   F1 wins (first on ties). Test flights are scored once, with that threshold.
4. Also reported: the threshold meeting a false-alarm budget (default one alarm per
   flight-hour) on the clean validation flights.

Both thresholds are chosen by ``Detector.calibrate`` (``detectors.calibration``), so a
detector fitted outside this protocol is calibrated by the same rule.

A reduced training budget (``TrainingBudget``, the demo profile's) gives every method that
trains the same fraction of its own default budget: training epochs of the network
detectors, training windows of PCA and the SVM. Methods that fit closed-form statistics
(chi2, CUSUM, SPRT, BHT) are unchanged. The full budget (None) is the paper's.
"""

from __future__ import annotations

import inspect
import itertools
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from quadformer.detectors import Detector, get, make
from quadformer.detectors.calibration import best_f1_threshold, budget_threshold  # noqa: F401  (the protocol's)


@dataclass(frozen=True)
class Split:
    train: np.ndarray
    val: np.ndarray
    test: np.ndarray
    labelled: np.ndarray   # training flights whose labels the methods may use

    def frames(self, flights: pd.DataFrame) -> "SplitFrames":
        """The rows of each part (index reset) and the training labels methods may use."""
        part = {k: flights[flights.flight_id.isin(getattr(self, k))].reset_index(drop=True)
                for k in ("train", "val", "test")}
        return SplitFrames(**part, y_train=training_labels(part["train"], self.labelled))


@dataclass(frozen=True)
class SplitFrames:
    train: pd.DataFrame
    val: pd.DataFrame
    test: pd.DataFrame
    y_train: np.ndarray    # label per training step, -1 on flights whose labels are withheld


def split_flights(scenarios: pd.DataFrame, seed: int, fractions=(0.6, 0.2, 0.2),
                  label_fraction: float = 0.2) -> Split:
    """Split flights (not windows) by seed, stratified by attacked / clean.

    When ``scenarios`` has a ``group`` column (flights replayed from one log segment, say),
    whole groups go to one part, stratified by whether a group holds an attacked flight: no
    recording is seen in training and again in test."""
    if not np.isclose(sum(fractions), 1.0) or min(fractions) <= 0:
        raise ValueError(f"split fractions must be positive and sum to 1, got {fractions}")
    if not 0.0 <= label_fraction <= 1.0:
        raise ValueError(f"label_fraction must be in [0, 1], got {label_fraction}")
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(0x5917,)))
    if "group" in scenarios.columns:
        keys = scenarios.groupby("group", sort=True)["attacked"].any()
        members = scenarios.groupby("group", sort=True)["flight_id"].apply(lambda v: np.sort(v.to_numpy()))
        units = pd.DataFrame({"flight_id": np.arange(len(keys)), "attacked": keys.to_numpy()})
        sp = split_flights(units, seed, fractions, label_fraction)
        if not (len(sp.train) and len(sp.val) and len(sp.test)):
            raise ValueError(f"{len(units)} recording(s) ({int(units.attacked.sum())} with an attack) cannot be split "
                             "into training, validation and test by recording: import more logs, or import with "
                             "--no-group to split their replays like flights (optimistic)")
        expand = lambda idx: np.sort(np.concatenate([members.iloc[i] for i in idx] or [np.zeros(0, int)]))  # noqa: E731
        return Split(*(expand(getattr(sp, k)).astype(int) for k in ("train", "val", "test", "labelled")))
    parts: dict[str, list] = {"train": [], "val": [], "test": [], "labelled": []}
    for attacked in (True, False):
        ids = np.sort(scenarios.loc[scenarios["attacked"] == attacked, "flight_id"].to_numpy())
        ids = rng.permutation(ids)
        n = len(ids)
        n_val = int(round(fractions[1] * n))
        n_test = int(round(fractions[2] * n))
        n_train = n - n_val - n_test
        tr = ids[:n_train]
        parts["train"] += list(tr)
        parts["val"] += list(ids[n_train:n_train + n_val])
        parts["test"] += list(ids[n_train + n_val:])
        parts["labelled"] += list(tr[: int(round(label_fraction * len(tr)))])
    return Split(*(np.sort(np.array(parts[k], dtype=int)) for k in ("train", "val", "test", "labelled")))


def training_labels(train: pd.DataFrame, labelled: np.ndarray) -> np.ndarray:
    """Labels of the labelled training flights, -1 elsewhere."""
    y = train["label"].to_numpy().astype(np.int8).copy()
    y[~train["flight_id"].isin(labelled).to_numpy()] = -1
    return y


#: the training-budget parameters a ``TrainingBudget`` scales, where a method has them
BUDGET_PARAMS = ("epochs", "max_windows")


@dataclass(frozen=True)
class TrainingBudget:
    """A reduced training budget: ``fraction`` of every trained method's default training
    epochs and training windows (rounded, at least ``minimum``), the same rule for every
    method. ``name`` keys the tuned-model cache, so models trained on a reduced budget are
    never reused by a run on another budget."""
    name: str
    fraction: float
    minimum: int = 2

    def __post_init__(self) -> None:
        if not 0.0 < self.fraction <= 1.0:
            raise ValueError(f"fraction: must be in (0, 1], got {self.fraction}")

    def fixed(self, method: str) -> dict[str, int]:
        """The scaled parameters of ``method`` (empty for a method that trains nothing)."""
        defaults = default_params(get(method))
        return {k: max(self.minimum, int(round(self.fraction * defaults[k]))) for k in BUDGET_PARAMS
                if isinstance(defaults.get(k), int)}

    def describe(self) -> dict[str, Any]:
        return {"name": self.name, "fraction": self.fraction, "minimum": self.minimum,
                "scaled_parameters": list(BUDGET_PARAMS),
                "rule": "every trained method gets the same fraction of its default training epochs "
                        "(network detectors) and training windows (PCA, SVM); statistical tests unchanged"}


def default_params(cls: type) -> dict[str, Any]:
    """Default constructor arguments of a detector class (through subclasses that take ``**kw``)."""
    out: dict[str, Any] = {}
    for c in reversed(cls.__mro__):
        init = c.__dict__.get("__init__")
        if init is None:
            continue
        for name, p in inspect.signature(init).parameters.items():
            if p.default is not inspect.Parameter.empty:
                out[name] = p.default
    return out


@dataclass
class Tuned:
    detector: Detector      # calibrated: threshold_ (max validation F1) and budget_threshold_
    params: dict[str, Any]
    val_f1: float
    grid: list[dict[str, Any]] = field(default_factory=list)
    cached: bool = False    # loaded from a model cache instead of tuned now
    val_scores: np.ndarray | None = None   # the winner's scores of the validation flights (tuned now)


def grid_points(grid: dict[str, list[Any]]) -> list[dict[str, Any]]:
    keys = list(grid)
    return [dict(zip(keys, vals)) for vals in itertools.product(*(grid[k] for k in keys))] or [{}]


def tune(method: str, train: pd.DataFrame, y_train: np.ndarray, val: pd.DataFrame,
         gps_rate_hz: float = 10.0, budget_per_hour: float = 1.0,
         grid: dict[str, list[Any]] | None = None, device: str | None = None,
         budget: TrainingBudget | None = None, **fixed: Any) -> Tuned:
    """Steps 3 and 4 of the protocol for one method; the winner comes back calibrated.

    budget: a reduced training budget (its scaled parameters are recorded in ``Tuned.params``);
    None: the methods' defaults.

    device: the torch device network detectors train on (``cpu``, ``cuda``, ``cuda:N``; None:
    their default); it is not a hyper-parameter and is not recorded in ``Tuned.params``."""
    cls = get(method)
    if budget is not None:
        fixed = {**budget.fixed(method), **fixed}
    if device is not None and "device" in inspect.signature(cls.__init__).parameters:
        fixed_make = {**fixed, "device": device}
    else:
        fixed_make = fixed
    grid = cls.param_grid if grid is None else grid
    y_val = val["label"].to_numpy()
    best: tuple[Detector, dict[str, Any], float, float, np.ndarray] | None = None
    tried = []
    post_grid = cls.post_grid
    for point in grid_points(grid):
        fitted = make(method, **{**fixed_make, **point}).fit(train, y_train)
        # post-processing parameters (e.g. an alarm rule) need no refit
        for post in grid_points(post_grid):
            det = fitted.with_post(**post) if post else fitted
            s = det.decision_function(val)
            thr, f1 = best_f1_threshold(s, y_val)
            tried.append({**point, **post, "val_f1": f1, "threshold": thr})
            if best is None or f1 > best[3]:
                best = (det, {**fixed, **point, **post}, thr, f1, s)
    assert best is not None
    det, params, _, f1, scores = best
    det.calibrate(val, y_val, gps_rate_hz=gps_rate_hz, budget_per_hour=budget_per_hour, scores=scores)
    return Tuned(det, params, f1, tried, val_scores=scores)
