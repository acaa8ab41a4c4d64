"""One detector and one dataset through the library, as ``quadformer fit`` and ``evaluate``
run them: the model file records its split, and the evaluation's files agree with the
detector and the metrics."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from quadformer.dataset import Dataset
from quadformer.detectors import load
from quadformer.detectors.alarms import ALERT_COLUMNS
from quadformer.evaluation.metrics import evaluate
from quadformer.evaluation.protocol import split_flights
from quadformer.experiments.models import evaluate_model, fit_model


@pytest.fixture(scope="module")
def fitted(bias_dataset, tmp_path_factory):
    path = tmp_path_factory.mktemp("model") / "cusum.json"
    tuned = fit_model("cusum", bias_dataset, path, seed=1, label_fraction=1.0, data="ds")
    return tuned, path


def test_fit_model_saves_the_calibrated_detector_with_its_split(fitted, bias_dataset):
    tuned, path = fitted
    det = load(path)
    assert det.name == "cusum" and det.threshold_ == tuned.detector.threshold_
    cal = det.calibration_
    sp = split_flights(bias_dataset.scenarios, 1, label_fraction=1.0)
    assert cal["test_flights"] == sp.test.tolist() and cal["split_seed"] == 1 and cal["data"] == "ds"
    assert cal["sim_config"] == json.loads(json.dumps(bias_dataset.meta["config"]))   # the filter tuning


def test_evaluate_model_writes_scores_alerts_and_the_metrics_of_the_test_flights(fitted, bias_dataset, tmp_path):
    _, path = fitted
    det = load(path)
    ev = evaluate_model(det, bias_dataset, tmp_path / "ev", model=str(path), data="ds", test_only=True)
    f = bias_dataset.flights
    f = f[f.flight_id.isin(det.calibration_["test_flights"])].reset_index(drop=True)
    scores = pd.read_parquet(tmp_path / "ev" / "scores.parquet")
    assert list(scores.columns) == ["flight_id", "t", "score", "alarm", "label"]
    np.testing.assert_array_equal(scores.score, det.decision_function(f))
    np.testing.assert_array_equal(scores.alarm, (scores.score > det.threshold_).astype(np.int8))
    res = json.loads((tmp_path / "ev" / "results.json").read_text())
    assert res == json.loads(json.dumps(ev.results))
    assert res["flights"] == len(det.calibration_["test_flights"]) and res["steps"] == len(f)
    assert res["method"] == "cusum" and res["model"] == str(path) and res["data"] == "ds"
    assert res["provenance"]["seeds"] == {"split": 1} and res["provenance"]["profile"] is None   # the model's split
    offsets = np.linalg.norm(f[["atk_d_x", "atk_d_y", "atk_d_z"]].to_numpy(), axis=1)
    m = evaluate(f.flight_id.to_numpy(), f.t.to_numpy(), f.label.to_numpy(), scores.score.to_numpy(),
                 scores.alarm.to_numpy() == 1, gps_rate_hz=bias_dataset.gps_rate_hz, offsets=offsets)
    assert json.loads(json.dumps(m)) == res["metrics"] and ev.metrics is ev.results["metrics"]
    alerts = pd.read_csv(tmp_path / "ev" / "alerts.csv")
    assert list(alerts.columns) == list(ALERT_COLUMNS) and len(alerts) == len(ev.alerts) == res["alerts"]


def test_evaluate_model_without_labels_scores_without_metrics(fitted, bias_dataset, tmp_path):
    _, path = fitted
    det = load(path)
    unlabelled = Dataset(bias_dataset.flights.drop(columns=["label"]), bias_dataset.scenarios, bias_dataset.meta)
    ev = evaluate_model(det, unlabelled, tmp_path / "ev", typing="detector")
    assert ev.metrics is None and "metrics" not in json.loads((tmp_path / "ev" / "results.json").read_text())
    assert "label" not in pd.read_parquet(tmp_path / "ev" / "scores.parquet").columns
    assert ev.results["flights"] == bias_dataset.flights.flight_id.nunique()
    assert set(pd.read_csv(tmp_path / "ev" / "alerts.csv").attack_type) <= {"attack"}   # cusum does not classify
