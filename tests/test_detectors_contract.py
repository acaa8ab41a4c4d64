"""The contract every registered detector honours (run over all of them)."""

import numpy as np
import pytest

from quadformer.detectors import NotFittedError, available, load
from quadformer.detectors import make as _make
from quadformer.detectors.classical import Chi2Gate

METHODS = available()
# Short training keeps the suite fast; the contract does not depend on it.
_TINY_QF = {"window": 16, "d_model": 16, "heads": 2, "epochs": 1, "steps_per_epoch": 3, "batch_size": 32}
FAST = {"cnn": {"epochs": 3}, "lstm": {"epochs": 3},
        **{m: _TINY_QF for m in ("quadformer", "quadformer-noprior", "quadformer-nosup", "quadformer-nodisc")}}


def make(method, **kw):
    return _make(method, **{**FAST.get(method, {}), **kw})


@pytest.fixture(scope="module")
def data(bias_dataset):
    f = bias_dataset.flights
    train = f[f.flight_id.isin([0, 1, 2, 3])].reset_index(drop=True)
    test = f[f.flight_id.isin([4, 5])].reset_index(drop=True)
    return train, train.label.to_numpy(), test


def test_methods_registered():
    assert {"chi2", "cusum", "sprt", "bht", "svm", "cnn", "lstm", "quadformer", "quadformer-noprior",
            "quadformer-nosup", "quadformer-nodisc"} <= set(METHODS)


@pytest.mark.parametrize("method", METHODS)
def test_init_stores_params_and_fit_returns_self(method, data):
    train, y, test = data
    det = make(method)
    assert not hasattr(det, "fitted_")
    assert _make(method, **det.get_params()).get_params() == det.get_params()
    with pytest.raises(NotFittedError):
        det.decision_function(test)
    assert det.fit(train, y) is det
    s = det.decision_function(test)
    assert s.shape == (len(test),) and np.isfinite(s).all()
    with pytest.raises(NotFittedError, match="threshold"):
        det.predict(test)
    det.threshold_ = float(np.median(s))
    assert set(np.unique(det.predict(test))) <= {0, 1}


@pytest.mark.parametrize("method", METHODS)
def test_same_data_same_scores_and_flight_independence(method, data):
    train, y, test = data
    a = make(method).fit(train, y).decision_function(test)
    b = make(method).fit(train, y).decision_function(test)
    assert np.array_equal(a, b)
    det = make(method).fit(train, y)
    one = det.decision_function(test[test.flight_id == 5].reset_index(drop=True))
    # a flight scores the same alone or with others, up to rounding (float32 networks, BLAS): 1e-6
    assert np.allclose(one, a[test.flight_id.to_numpy() == 5], rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("method", METHODS)
def test_causal(method, data):
    """Appending future steps does not change past scores."""
    train, y, test = data
    det = make(method).fit(train, y)
    flight = test[test.flight_id == 4].reset_index(drop=True)
    full = det.decision_function(flight)
    for k in (1, 37, 120):
        # up to rounding that depends on how many rows are scored together (float32 networks): 1e-6
        assert np.allclose(det.decision_function(flight.iloc[:k]), full[:k], rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("method", METHODS)
def test_save_load_round_trip(method, data, tmp_path):
    train, y, test = data
    det = make(method).fit(train, y)
    det.threshold_ = 1.5
    back = load(det.save(tmp_path / "m.json"))
    assert np.array_equal(back.decision_function(test), det.decision_function(test))
    assert back.threshold_ == 1.5 and back.get_params() == det.get_params()


@pytest.mark.parametrize("method", METHODS)
def test_bad_input_is_named(method, data):
    train, y, test = data
    det = make(method).fit(train, y)
    bad = test.copy()
    bad.loc[5, "res_gps_nis"] = np.nan
    with pytest.raises(ValueError, match="non-finite residue in column res_gps_nis"):
        det.decision_function(bad)
    with pytest.raises(ValueError, match="missing columns"):
        det.decision_function(test.drop(columns=["res_gps_nis"]))


@pytest.mark.parametrize("method", ["cusum", "sprt", "bht"])
def test_streaming_equals_offline(method, data):
    train, y, test = data
    det = make(method).fit(train, y)
    flight = test[test.flight_id == 4].reset_index(drop=True)
    stream = det.stream()
    online = [stream.update(v) for v in flight.res_gps_nis]
    assert np.array_equal(np.array(online), det.decision_function(flight))


def test_unknown_method_named():
    with pytest.raises(KeyError, match="unknown detector 'nope'"):
        make("nope")


def test_chi2_detects_bias_better_than_chance(data):
    train, y, test = data
    s = Chi2Gate().fit(train, y).decision_function(test)
    lab = test.label.to_numpy() == 1
    assert s[lab].mean() > 2 * s[~lab].mean()
    assert Chi2Gate.gate_threshold(5.0) > 30
