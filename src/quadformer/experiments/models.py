"""One detector and one dataset: fit a detector into a model file, and score a dataset with
a model file (scores, alerts and, where the dataset has labels, metrics).

``fit_model``: the protocol's split of the dataset's flights, the method tuned on the
training flights and calibrated on the validation flights, saved with what it was fit on
(dataset, split seed, test flights, the simulation whose filter made the residues).
``evaluate_model``: a fitted detector over a dataset's flights (or the test flights of its
own split), written to a directory: ``scores.parquet`` (flight_id, t, score, alarm and
label where the dataset has labels), ``alerts.csv`` and ``results.json``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from quadformer.dataset import Dataset
from quadformer.detectors import alerts_from_scores, write_alerts
from quadformer.detectors.alarms import Alert
from quadformer.detectors.attack_types import alert_typer
from quadformer.evaluation.metrics import evaluate
from quadformer.evaluation.protocol import Tuned, split_flights, tune
from quadformer.experiments.provenance import provenance
from quadformer.io import atomic_path, write_json


def fit_model(method: str, ds: Dataset, out: str | Path, seed: int = 0, label_fraction: float = 0.2,
              data: str | None = None) -> Tuned:
    """Tune ``method`` on the training flights of ``ds``'s split (``seed``; labels of
    ``label_fraction`` of them), calibrate it on the validation flights and save it to ``out``.
    ``data``: the dataset's location, recorded in the model. ValueError from the tuning (a
    method that cannot run on this data)."""
    sp = split_flights(ds.scenarios, seed, label_fraction=label_fraction)
    parts = sp.frames(ds.flights)
    tuned = tune(method, parts.train, parts.y_train, parts.val, gps_rate_hz=ds.gps_rate_hz)
    det = tuned.detector
    det.calibrate(det.threshold_, det.budget_threshold_, data=data, split_seed=seed,
                  label_fraction=label_fraction, test_flights=sp.test.tolist(),
                  sim_config=ds.meta.get("config"))      # the filter tuning its residues came from
    det.save(out)
    return tuned


@dataclass
class Evaluation:
    results: dict[str, Any]     # what results.json holds: model, data, method, threshold, counts, metrics
    alerts: list[Alert]
    out: Path

    @property
    def metrics(self) -> dict[str, Any] | None:
        return self.results.get("metrics")


def evaluate_model(detector, ds: Dataset, out: str | Path, model: str = "", data: str = "",
                   test_only: bool = False, typing: str = "shape") -> Evaluation:
    """Score ``ds`` (only the test flights of the split the detector was fit with where
    ``test_only``) with a calibrated ``detector``; alerts typed by ``typing``
    (``detectors.attack_types.TYPINGS``); point-wise and event metrics where the flights are
    labelled. Writes scores.parquet, alerts.csv and results.json into ``out``. ``model`` and
    ``data`` name the model file and dataset in results.json. ValueError from the detector
    when the flights lack what it reads."""
    f = ds.flights
    if test_only:
        f = f[f.flight_id.isin(getattr(detector, "calibration_", {}).get("test_flights", []))].reset_index(drop=True)
    s = detector.decision_function(f)
    alarms = (s > detector.threshold_).astype(np.int8)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    table = f[["flight_id", "t"]].copy()
    table["score"] = s
    table["alarm"] = alarms
    res: dict[str, Any] = {"model": model, "data": data, "method": detector.name, "threshold": detector.threshold_,
                           "flights": int(f.flight_id.nunique()), "steps": int(len(f))}
    if "label" in f.columns:
        table["label"] = f["label"].to_numpy()
        offsets = np.linalg.norm(f[["atk_d_x", "atk_d_y", "atk_d_z"]].to_numpy(), axis=1) \
            if "atk_d_x" in f.columns else None
        res["metrics"] = evaluate(f.flight_id.to_numpy(), f.t.to_numpy(), f.label.to_numpy(), s, alarms == 1,
                                  gps_rate_hz=ds.gps_rate_hz, offsets=offsets)
    with atomic_path(out / "scores.parquet") as tmp:
        table.to_parquet(tmp, index=False)
    alerts = alerts_from_scores(f, s, detector, typer=alert_typer(f, typing))
    write_alerts(alerts, out / "alerts.csv")
    res["alerts"] = len(alerts)
    split = (getattr(detector, "calibration_", None) or {}).get("split_seed")
    res["provenance"] = provenance({} if split is None else {"split": split}, None)
    write_json(out / "results.json", res)
    return Evaluation(res, alerts, out)
