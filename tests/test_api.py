"""The public API: scikit-learn parameter conventions for every registered detector,
calibration on validation flights, the package's lazy re-exports, and the README's quick start."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from sklearn.base import clone

import quadformer
from quadformer import detectors
from quadformer.detectors import NotFittedError, available, make
from quadformer.detectors.calibration import best_f1_threshold, budget_threshold
from quadformer.evaluation.protocol import split_flights, tune

METHODS = available()
EXAMPLE = Path(__file__).resolve().parents[1] / "docs" / "quickstart_example.py"


def _changed(det):
    """A parameter set off its default, where the detector has one to set."""
    params = det.get_params()
    return {"seed": 7} if "seed" in params else {"drift": 2.5} if "drift" in params else {}


@pytest.fixture(scope="module")
def parts(bias_dataset):
    """The fixture's flights split by flight (each part holds an attacked and a clean flight)."""
    p = split_flights(bias_dataset.scenarios, seed=0).frames(bias_dataset.flights)
    for part in (p.train, p.val, p.test):
        assert set(part.groupby("flight_id").label.max()) == {0, 1}
    return p


@pytest.mark.parametrize("method", METHODS)
def test_clone_gives_an_unfitted_detector_with_the_same_params(method):
    det = make(method)
    det.set_params(**_changed(det))
    copy = clone(det)
    assert type(copy) is type(det) and copy is not det
    assert copy.get_params() == det.get_params()
    assert not getattr(copy, "fitted_", False)


def test_clone_of_a_fitted_calibrated_detector_is_unfitted(parts):
    det = make("cusum", drift=2.0).fit(parts.train).calibrate(parts.val)
    copy = clone(det)
    assert copy.get_params() == {"drift": 2.0}
    assert not hasattr(copy, "threshold_") and not hasattr(copy, "scale_")
    with pytest.raises(NotFittedError):
        copy.decision_function(parts.test)


@pytest.mark.parametrize("method", METHODS)
def test_get_params_deep_and_set_params_in_place(method):
    det = make(method)
    params = det.get_params()
    assert det.get_params(deep=True) == det.get_params(deep=False) == params
    assert det.set_params(**params) is det and det.get_params() == params
    change = _changed(det)
    assert det.set_params(**change) is det
    assert det.get_params() == {**params, **change}
    with pytest.raises(ValueError, match="invalid parameter"):
        det.set_params(no_such_parameter=1)


def test_set_params_refuses_what_an_ablation_fixes():
    with pytest.raises(ValueError, match="supervised"):
        make("quadformer-nosup").set_params(supervised=True)


def test_fit_calibrate_predict(parts, bias_dataset):
    det = make("cusum")
    assert det.fit(parts.train, parts.y_train) is det and det.calibrate(parts.val) is det
    s = det.decision_function(parts.val)
    assert det.threshold_ == best_f1_threshold(s, parts.val.label.to_numpy())[0]
    # the budget threshold: the clean validation flights, their hours from the GPS rate
    fid = parts.val.flight_id.to_numpy()
    clean = np.setdiff1d(np.unique(fid), np.unique(fid[parts.val.label == 1]))
    hours = np.isin(fid, clean).sum() / bias_dataset.gps_rate_hz / 3600
    assert det.budget_threshold_ == budget_threshold(s, fid, clean, hours)
    alarms = det.predict(parts.test)
    assert alarms.dtype == np.int8 and alarms.shape == (len(parts.test),) and set(np.unique(alarms)) <= {0, 1}
    # a floor: most attacked test steps raise an alarm, the clean test flight hardly any
    y = parts.test.label.to_numpy() == 1
    clean = parts.test.groupby("flight_id").label.transform("max").to_numpy() == 0
    assert alarms[y].mean() > 0.8 and alarms[clean].mean() < 0.02
    budget = make("cusum").fit(parts.train, parts.y_train).calibrate(parts.val, criterion="budget")
    assert budget.threshold_ == budget.budget_threshold_ == det.budget_threshold_


def test_calibrate_is_what_the_protocol_runs(parts):
    tuned = tune("cusum", parts.train, parts.y_train, parts.val, grid={"drift": [1.0]})
    det = make("cusum").fit(parts.train, parts.y_train).calibrate(parts.val, gps_rate_hz=10.0)
    assert (det.threshold_, det.budget_threshold_) == (tuned.detector.threshold_, tuned.detector.budget_threshold_)


def test_calibrate_errors_and_a_given_threshold(parts):
    with pytest.raises(NotFittedError):
        make("cusum").calibrate(parts.val)
    det = make("cusum").fit(parts.train)
    with pytest.raises(ValueError, match="labels"):
        det.calibrate(parts.val.drop(columns="label"))
    with pytest.raises(ValueError, match="criterion"):
        det.calibrate(parts.val, criterion="auc")
    with pytest.raises(TypeError):
        det.calibrate(3.0, criterion="budget")
    assert det.calibrate(3.0, 4.0, split_seed=0) is det
    assert (det.threshold_, det.budget_threshold_, det.calibration_) == (3.0, 4.0, {"split_seed": 0})
    assert det.calibrate(2.0, budget_threshold=5.0).budget_threshold_ == 5.0
    with pytest.raises(TypeError):
        det.calibrate(parts.val, budget_threshold=5.0)
    # no labels: every validation flight counts as clean for the false-alarm budget
    clean = parts.val[parts.val.groupby("flight_id").label.transform("max") == 0]
    a = det.calibrate(clean.drop(columns="label"), criterion="budget").threshold_
    assert a == det.calibrate(clean, criterion="budget").threshold_


def test_detectors_and_package_exports():
    for name in ("make", "load", "Detector", "alerts_from_scores", "available", "register"):
        assert name in detectors.__all__
    assert all(hasattr(detectors, n) for n in detectors.__all__)
    for name in ("read_log", "detect_log", "Monitor", "make", "load", "simulate", "SimConfig", "load_dataset"):
        assert name in quadformer.__all__ and name in dir(quadformer)
    assert quadformer.make is detectors.make and quadformer.load is detectors.load
    from quadformer.live.monitor import Monitor
    from quadformer.logs import read_log
    from quadformer.logs.detect import detect_log
    assert (quadformer.Monitor, quadformer.read_log, quadformer.detect_log) == (Monitor, read_log, detect_log)
    with pytest.raises(AttributeError):
        quadformer.no_such_name  # noqa: B018


def test_importing_the_package_loads_neither_torch_nor_its_layers():
    code = ("import sys, quadformer; "
            "print(sorted(m for m in sys.modules if m == 'torch' or m.startswith('quadformer.')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_quick_start_example_runs(bias_dataset, monkeypatch, capsys):
    """The README's six lines, as written; ``simulate`` is served from the session's fixture,
    which holds the very flights the example asks for (flight i depends only on the config,
    the seed and i)."""
    text = EXAMPLE.read_text()
    code = [line for line in text.splitlines() if line.strip() and not line.startswith("#")]
    assert len(code) == 6

    def simulate(cfg, progress=False):
        assert cfg == bias_dataset.config
        return bias_dataset

    monkeypatch.setattr(quadformer, "simulate", simulate)
    exec(compile(text, str(EXAMPLE), "exec"), {"__name__": "__main__"})
    out = capsys.readouterr().out.split()
    assert out[:2] == ["label", "alarm"] and len(out) == 3 + 3 * 2    # a row per test flight
