"""The contract every registered detector honours (run over all of them)."""

import numpy as np
import pandas as pd
import pytest

from quadformer.detectors import NotFittedError, available, load
from quadformer.detectors import make as _make
from quadformer.detectors.classical import Chi2Gate

METHODS = available()
# Short training and a short context (48 steps: 4 patches of 8, then 16 single steps) keep the
# suite fast; the contract does not depend on them.
SHORT = {"window": 48, "fine": 16, "patch": 8}
_TINY_QF = {**SHORT, "d_model": 16, "heads": 2, "epochs": 1, "steps_per_epoch": 3, "batch_size": 32}
FAST = {"cnn": {**SHORT, "epochs": 3}, "lstm": {**SHORT, "epochs": 3}, "svm": SHORT, "pca": SHORT,
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
    assert {"chi2", "cusum", "sprt", "bht", "pca", "svm", "cnn", "lstm", "quadformer", "quadformer-noprior",
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
    det.calibrate(float(np.median(s)))
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
    det.calibrate(1.5, 2.5)
    back = load(det.save(tmp_path / "m.json"))
    assert np.array_equal(back.decision_function(test), det.decision_function(test))
    assert back.threshold_ == 1.5 and back.budget_threshold_ == 2.5 and back.get_params() == det.get_params()


@pytest.mark.parametrize("method", METHODS)
def test_bad_input_is_named(method, data):
    train, y, test = data
    det = make(method).fit(train, y)
    col = "res_gps_nis" if "res_gps_nis" in det.features_ else det.features_[0]
    bad = test.copy()
    bad.loc[5, col] = np.nan
    with pytest.raises(ValueError, match=f"non-finite residue in column {col}"):
        det.decision_function(bad)
    with pytest.raises(ValueError, match="missing columns"):
        det.decision_function(test.drop(columns=[col]))


@pytest.mark.parametrize("method", METHODS)
def test_stream_of_several_flights_equals_offline(method, data):
    """``stream(n)`` steps n flights together and gives each flight's offline scores and
    alarms: exactly for the classical statistics (same arithmetic), to float32 rounding for the
    networks (one window per call online, batches offline)."""
    train, y, test = data
    det = make(method).fit(train, y)
    offline = det.decision_function(test)
    det.calibrate(float(np.percentile(offline, 70)))
    ids = test.flight_id.unique()
    n_steps = len(test) // len(ids)
    # the row as a driver gives it: residues and the fix as received (extra columns are ignored)
    cols = {c: test[c].to_numpy().reshape(len(ids), n_steps) for c in test.columns if c.startswith(("res_", "gps_"))}
    stream = det.stream(len(ids))
    steps = [stream.update({c: v[:, j] for c, v in cols.items()}) for j in range(n_steps)]
    online = np.stack([s.score for s in steps], 1).reshape(-1)
    alarms = np.stack([s.alarm for s in steps], 1).reshape(-1)
    if method in ("chi2", "cusum", "sprt", "bht"):
        assert np.array_equal(online, offline)
    else:
        np.testing.assert_allclose(online, offline, rtol=1e-5, atol=1e-6)
    near = np.abs(offline - det.threshold_) < 1e-5      # rounding may flip only these
    assert np.array_equal(alarms[~near], (offline > det.threshold_)[~near])
    with pytest.raises(ValueError, match="missing"):
        det.stream(len(ids)).update({"t": np.zeros(len(ids))})
    with pytest.raises(ValueError, match="finite values"):
        det.stream(1).update(np.full(len(det.features_), np.nan))


def _nis(z, det):
    """A one-flight frame whose normalised NIS is z."""
    return pd.DataFrame({"flight_id": 0, "t": np.arange(len(z)) / 10.0, "res_gps_nis": np.asarray(z) * det.scale_})


Z = [2.0, 9.0, 14.0, 3.0, 30.0, 0.5, 0.0]


def test_cusum_hand_case(data):
    train, y, _ = data
    det = make("cusum", drift=1.0).fit(train, y)
    # S = max(0, S + z - b), b = 6 + 1 * sqrt(12) = 9.464102: by hand
    expected = [0.0, 0.0, 4.535898, 0.0, 20.535898, 11.571797, 2.107695]
    assert det.decision_function(_nis(Z, det)) == pytest.approx(expected, abs=1e-6)


def test_velocity_reference_tests_hand_case(data):
    train, y, _ = data
    det = make("cusum-vref", drift=1.0).fit(train, y)
    assert det.features_ == ["res_ref_vmean_x", "res_ref_vmean_y", "res_ref_vmean_z"] and det.scale_ > 0
    # the statistic is the sum of squares of the three whitened components: split z*scale over them
    v = np.sqrt(np.asarray(Z) * det.scale_ / 3.0)
    frame = pd.DataFrame({"flight_id": 0, "t": np.arange(len(Z)) / 10.0, "res_ref_vmean_x": v,
                          "res_ref_vmean_y": -v, "res_ref_vmean_z": v})
    # S = max(0, S + z - b), b = 3 + 1 * sqrt(6) = 5.449490: by hand
    expected = [0.0, 3.550510, 12.101021, 9.651531, 34.202041, 29.252551, 23.803062]
    assert det.decision_function(frame) == pytest.approx(expected, abs=1e-6)
    gate = make("chi2-vref").fit(train, y)
    assert gate.decision_function(frame) == pytest.approx(np.asarray(Z) * det.scale_ / gate.scale_, rel=1e-12)


def test_reference_cusum_hand_case(data):
    """``cusum-ref``: the statistic is the sum of squares of the whitened 5-s position change and
    the whitened 10-s mean velocity difference (6 columns, 6 dof), the same CUSUM as ``cusum``."""
    train, y, _ = data
    det = make("cusum-ref", drift=1.0).fit(train, y)
    assert det.features_ == ["res_ref_h5_px", "res_ref_h5_py", "res_ref_h5_pz",
                             "res_ref_vmean_x", "res_ref_vmean_y", "res_ref_vmean_z"] and det.scale_ > 0
    # z * scale split over the six columns, half of it in the position step, with mixed signs
    v = np.sqrt(np.asarray(Z) * det.scale_ / 6.0)
    frame = pd.DataFrame({"flight_id": 0, "t": np.arange(len(Z)) / 10.0,
                          **{c: (-v if i % 2 else v) for i, c in enumerate(det.features_)}})
    # the velocity test's columns alone would not give this: every column counts
    assert det.decision_function(frame) == pytest.approx(
        [0.0, 0.0, 4.535898, 0.0, 20.535898, 11.571797, 2.107695], abs=1e-6)   # b = 6 + sqrt(12), as cusum's case
    frame[list(det.features_[:3])] = 0.0
    assert det.decision_function(frame)[4] == pytest.approx(max(0.0, 15.0 - 9.464102), abs=1e-6)


def test_a_model_saved_with_the_former_scale_name_loads(data, tmp_path):
    import json

    train, y, test = data
    det = make("cusum", drift=0.5).fit(train, y)
    path = det.save(tmp_path / "cusum.json")
    doc = json.loads(path.read_text())
    text = json.dumps(doc).replace('"scale_"', '"nis_scale_"')     # as models were saved before
    assert "nis_scale_" in text
    path.write_text(text)
    assert np.array_equal(load(path).decision_function(test), det.decision_function(test))


def test_sprt_hand_case(data):
    train, y, _ = data
    det = make("sprt", inflation=2.0, alpha=0.01, beta=0.01).fit(train, y)
    llr = lambda z: -6 * np.log(2.0) + 0.5 * z * (1 - 1 / 4)   # noqa: E731
    lo, hi = np.log(0.01 / 0.99), np.log(0.99 / 0.01)            # -4.595, Wald's B 4.595
    # llr(z) = -6 log 2 + 3 z / 8: z = 2 -> -3.41; 9 -> -0.78 (sum -4.19); 14 -> +1.09 (-3.10);
    # 3 -> -3.03 (-6.13 <= lo: restart at 0); 30 -> +7.09 (past B, not held); 0.5 -> -3.97 (3.12)
    s, expected = 0.0, []
    for z in Z:
        s = s + llr(z)
        s = 0.0 if s <= lo else s
        expected.append(s)
    assert expected[3] == 0.0 and expected[4] > hi + 2 and expected[5] > 3
    assert det.decision_function(_nis(Z, det)) == pytest.approx(expected, abs=1e-12)


@pytest.mark.parametrize("method, params, named", [
    ("sprt", {"inflation": 1.0}, "inflation must lie in \\(1, inf\\), got 1.0"),
    ("sprt", {"alpha": 0.0}, "alpha must lie in \\(0, 1\\)"),
    ("bht", {"end_rate": 1.0}, "end_rate must lie in \\(0, 1\\)"),
    ("bht", {"onset_rate": float("nan")}, "onset_rate must lie in \\(0, 1\\), got nan"),
])
def test_variance_inflation_parameters_refused_at_fit(data, method, params, named):
    train, y, _ = data
    with pytest.raises(ValueError, match=f"{method}: {named}"):
        make(method, **params).fit(train, y)


def test_bht_hand_case(data):
    train, y, _ = data
    det = make("bht", inflation=3.0, onset_rate=0.01, end_rate=0.05).fit(train, y)
    p = 0.01                                        # prior belief before the first step: the onset rate
    expected = []
    for z in Z:
        prior = p * 0.95 + (1 - p) * 0.01
        f1 = (1 / 3.0) ** 6 * np.exp(-z / (2 * 9))  # attacked: N(0, 9 I6), up to the common factor
        f0 = np.exp(-z / 2)                         # nominal (common factors cancel)
        post = prior * f1 / (prior * f1 + (1 - prior) * f0)
        expected.append(np.log(post / (1 - post)))
        p = post
    # a fix far off: its posterior is 1 in floating point, its log-odds past any fixed ceiling
    prior = p * 0.95 + (1 - p) * 0.01
    expected.append(np.log(prior / (1 - prior)) - 6 * np.log(3.0) + 0.5 * 400.0 * (1 - 1 / 9))
    assert expected[-1] > 150
    assert det.decision_function(_nis(Z + [400.0], det)) == pytest.approx(expected, rel=1e-9, abs=1e-9)


def test_unknown_method_named():
    with pytest.raises(KeyError, match="unknown detector 'nope'"):
        make("nope")


def test_chi2_detects_bias_better_than_chance(data):
    train, y, test = data
    s = Chi2Gate().fit(train, y).decision_function(test)
    lab = test.label.to_numpy() == 1
    assert s[lab].mean() > 2 * s[~lab].mean()
    assert Chi2Gate.gate_threshold(5.0) > 30


def test_pca_score_is_the_reconstruction_error_of_a_reference_pca(data):
    """The PCA detector against scikit-learn's PCA fitted on the same training windows (every
    window not known to be attacked): the mean squared residual of each test window, to 1e-9."""
    from sklearn.decomposition import PCA

    from quadformer.detectors.windows import Windows

    train, y, test = data
    det = make("pca", n_components=4, max_windows=10**6).fit(train, y)

    def tokens(w):   # SHORT by hand: 4 means of 8 steps (float32, as the windows), then the last 16 steps
        means = w[:, :32].astype(float).reshape(len(w), 4, 8, -1).mean(2).astype(np.float32)
        return np.concatenate([means, w[:, 32:]], 1).reshape(len(w), -1).astype(float)

    win = Windows(train, det.features_, det.normalizer_, det.window)
    ref = PCA(n_components=4, svd_solver="full").fit(tokens(win[np.nonzero(y != 1)[0]]))
    Zt = tokens(Windows(test, det.features_, det.normalizer_, det.window)[np.arange(len(test))])
    want = np.mean((Zt - ref.inverse_transform(ref.transform(Zt))) ** 2, axis=1)
    np.testing.assert_allclose(det.decision_function(test), want, rtol=1e-9, atol=1e-12)
    # attacked windows reconstruct worse than clean ones
    s = det.decision_function(test)
    lab = test.label.to_numpy() == 1
    assert s[lab].mean() > s[~lab].mean()


def test_pca_fits_of_the_grid_share_one_decomposition(data):
    """Tuning fits PCA once per n_components on the same windows: the directions of a smaller
    fit are the leading directions of a larger one, whichever comes first, and a new seed
    (other windows) decomposes anew."""
    train, y, _ = data
    big = make("pca", n_components=16).fit(train, y)
    small = make("pca", n_components=4).fit(train, y)
    np.testing.assert_array_equal(small.components_, big.components_[:4])
    again = make("pca", n_components=16).fit(train, y)
    np.testing.assert_array_equal(again.components_, big.components_)
    other = make("pca", n_components=4, max_windows=300, seed=1).fit(train, y)
    assert not np.allclose(np.abs(other.components_), np.abs(small.components_))
