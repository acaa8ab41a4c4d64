"""Learning baselines: windows, normalisation, augmentation, training reproducibility."""

import json

import numpy as np
import pandas as pd
import pytest
import torch

from quadformer.detectors import load, make
from quadformer.detectors.base import check_residues
from quadformer.detectors.windows import RESIDUE_FEATURES, AxisSymmetry, Normalizer, Windows


def _two_flights():
    rng = np.random.default_rng(0)
    n = 10
    df = pd.DataFrame({"flight_id": np.repeat([7, 9], n), "t": np.tile(np.arange(n) / 10, 2)})
    for c in ("res_gps_nis", "res_gps_w_px"):
        df[c] = rng.standard_normal(2 * n)
    return df


def test_windows_are_causal_and_per_flight():
    df = _two_flights()
    cols = ["res_gps_nis", "res_gps_w_px"]
    norm = Normalizer().fit(check_residues(df, cols))
    vals = norm.transform(df[cols].to_numpy())
    w = Windows(df, cols, norm, width=4)
    win = w[np.arange(len(df))]
    assert win.shape == (20, 4, 2)
    assert np.array_equal(win[5], vals[2:6])                        # steps k-3..k
    assert np.array_equal(win[11], np.r_[np.zeros((2, 2)), vals[10:12]])   # second flight starts padded
    # appending future steps leaves past windows unchanged
    short = Windows(df.iloc[:7], cols, norm, width=4)[np.arange(7)]
    assert np.array_equal(short, win[:7])


def test_normaliser_is_fitted_on_training_rows_only(bias_dataset):
    f = bias_dataset.flights
    train = f[f.flight_id < 4].reset_index(drop=True)
    test = f[f.flight_id >= 4].reset_index(drop=True)
    det = make("cnn", epochs=2).fit(train, train.label.to_numpy())
    cols = det.features_
    assert np.allclose(det.normalizer_.mean_, np.median(train[cols].to_numpy(), axis=0))
    assert not np.allclose(det.normalizer_.mean_, np.median(test[cols].to_numpy(), axis=0))
    before = det.normalizer_.mean_.copy()
    det.decision_function(test)
    assert np.array_equal(det.normalizer_.mean_, before)
    assert "res_gps_s_px" not in cols and set(cols) <= set(RESIDUE_FEATURES)


def test_axis_symmetry_flips_and_swaps_consistently():
    feats = ["res_gps_r_px", "res_gps_r_py", "res_gps_nis", "res_gps_w_px", "res_gps_w_py", "res_vio_r_vz"]
    aug = AxisSymmetry(feats)
    x = torch.arange(1, 1 + 2 * 3 * 6, dtype=torch.float32).reshape(2, 3, 6)
    out = aug(x.clone(), np.random.default_rng(3))
    for b in range(2):
        # the NIS (sign-free) never changes; every other feature keeps its magnitude set
        assert torch.equal(out[b, :, 2], x[b, :, 2])
        assert sorted(out[b].abs().flatten().tolist()) == sorted(x[b].abs().flatten().tolist())
        # raw and whitened px share one sign (or move together to py under a swap)
        r = out[b, :, 0] / x[b, :, 0]
        w = out[b, :, 3] / x[b, :, 3]
        assert torch.all(r.abs() == 1) == torch.all(w.abs() == 1)


@pytest.mark.parametrize("method", ["cnn", "lstm"])
def test_training_is_reproducible_and_leaves_global_rng_alone(method, bias_dataset):
    f = bias_dataset.flights
    train = f[f.flight_id < 4].reset_index(drop=True)
    state = torch.get_rng_state()
    a = make(method, epochs=3, seed=5).fit(train, train.label.to_numpy())
    assert torch.equal(torch.get_rng_state(), state)
    b = make(method, epochs=3, seed=5).fit(train, train.label.to_numpy())
    c = make(method, epochs=3, seed=6).fit(train, train.label.to_numpy())
    sa, sb, sc = (d.decision_function(f) for d in (a, b, c))
    assert np.array_equal(sa, sb)
    assert not np.array_equal(sa, sc)
    assert len(a.history_) >= 1 and {"train_loss", "holdout_loss"} <= set(a.history_[0])


def test_checkpoint_is_state_dict_plus_json(bias_dataset, tmp_path):
    f = bias_dataset.flights
    train = f[f.flight_id < 4].reset_index(drop=True)
    det = make("lstm", epochs=2).fit(train, train.label.to_numpy())
    det.threshold_ = 0.25
    det.save(tmp_path / "m.json")
    doc = json.loads((tmp_path / "m.json").read_text())
    assert doc["method"] == "lstm" and doc["params"]["hidden"] == 64
    weights = torch.load(tmp_path / "m.pt", weights_only=True)
    assert all(isinstance(v, torch.Tensor) for v in weights.values())
    back = load(tmp_path / "m.json")
    assert np.array_equal(back.decision_function(f), det.decision_function(f))
    (tmp_path / "m.pt").unlink()
    with pytest.raises(FileNotFoundError, match="weights of m.json are missing"):
        load(tmp_path / "m.json")


def test_unlabelled_training_is_refused(bias_dataset):
    f = bias_dataset.flights
    with pytest.raises(ValueError, match="no labelled training flight"):
        make("cnn").fit(f, np.full(len(f), -1))
    with pytest.raises(ValueError, match="needs labels"):
        make("svm").fit(f)
