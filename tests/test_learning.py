"""Learning baselines: windows, normalisation, augmentation, training reproducibility."""

import json
import pathlib

import numpy as np
import pandas as pd
import pytest
import torch

from quadformer.detectors import load, make
from quadformer.detectors.base import check_residues
from quadformer.detectors.windows import AxisSymmetry, Normalizer, Windows
from quadformer.estimator.schema import DETECTOR_FEATURES


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
    assert "res_gps_s_px" not in cols and set(cols) <= set(DETECTOR_FEATURES)


def test_axis_symmetry_flips_and_swaps_consistently():
    feats = ["res_gps_r_px", "res_gps_r_py", "res_gps_nis", "res_gps_w_px", "res_gps_w_py", "res_vio_r_vz"]
    aug = AxisSymmetry(feats)
    n = 200
    x = torch.arange(1, 1 + n * 3 * 6, dtype=torch.float32).reshape(n, 3, 6)   # every value distinct
    out = aug(x.clone(), np.random.default_rng(3))
    swapped, signs_x, signs_z = [], [], []
    for b in range(n):
        # the NIS (sign-free) never changes
        assert torch.equal(out[b, :, 2], x[b, :, 2])
        # raw px lands on px or on py (a swap), with one sign over the window
        sw = bool(torch.equal(out[b, :, 1].abs(), x[b, :, 0]))
        assert sw or torch.equal(out[b, :, 0].abs(), x[b, :, 0])
        src_x, src_y = (1, 0) if sw else (0, 1)
        sx = out[b, :, src_x] / x[b, :, 0]
        sy = out[b, :, src_y] / x[b, :, 1]
        assert torch.all(sx == sx[0]) and torch.all(sy == sy[0]) and abs(sx[0]) == 1 and abs(sy[0]) == 1
        # the whitened innovation of an axis follows its raw one: same sign, same destination
        assert torch.equal(out[b, :, 3 + src_x], x[b, :, 3] * sx[0])
        assert torch.equal(out[b, :, 3 + src_y], x[b, :, 4] * sy[0])
        sz = out[b, :, 5] / x[b, :, 5]
        assert torch.all(sz.abs() == 1) and torch.all(sz == sz[0])
        swapped.append(sw)
        signs_x.append(float(sx[0]))
        signs_z.append(float(sz[0]))
    # both outcomes of every random choice occur, each about half of the time
    for outcomes in (swapped, np.array(signs_x) > 0, np.array(signs_z) > 0):
        assert 0.35 < np.mean(outcomes) < 0.65


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


def test_training_is_ieee_float32_inside_and_leaves_the_settings_alone():
    # cuDNN's TF32 default trained an LSTM and a CNN 0.08 F1 below the CPU's on a GPU (training.py)
    from quadformer.detectors.neural.training import ieee_fp32
    cudnn = torch.backends.cudnn
    before = (cudnn.conv.fp32_precision, cudnn.rnn.fp32_precision)
    assert before == ("tf32", "tf32")          # torch's default, which training must not keep
    with pytest.raises(RuntimeError):
        with ieee_fp32():
            assert (cudnn.conv.fp32_precision, cudnn.rnn.fp32_precision) == ("ieee", "ieee")
            raise RuntimeError("a failed epoch")
    assert (cudnn.conv.fp32_precision, cudnn.rnn.fp32_precision) == before


def test_checkpoint_is_state_dict_plus_json(bias_dataset, tmp_path):
    f = bias_dataset.flights
    train = f[f.flight_id < 4].reset_index(drop=True)
    det = make("lstm", epochs=2).fit(train, train.label.to_numpy())
    det.calibrate(0.25)
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


class _Payload:
    """An object whose unpickling would run code (it writes a file)."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (pathlib.Path.touch, (pathlib.Path(self.path),))


def test_loading_weights_that_hold_pickled_objects_is_refused(bias_dataset, tmp_path):
    f = bias_dataset.flights
    train = f[f.flight_id < 4].reset_index(drop=True)
    det = make("cnn", epochs=1).fit(train, train.label.to_numpy())
    det.save(tmp_path / "m.json")
    marker = tmp_path / "code-ran"
    state = dict(det.model_.state_dict())
    state["extra"] = _Payload(marker)
    torch.save(state, tmp_path / "m.pt")
    with pytest.raises(ValueError, match="m.pt: not a plain tensor state dict"):
        load(tmp_path / "m.json")
    assert not marker.exists()
    (tmp_path / "m.pt").write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match="not a plain tensor state dict"):
        load(tmp_path / "m.json")


def test_unlabelled_training_is_refused(bias_dataset):
    f = bias_dataset.flights
    with pytest.raises(ValueError, match="no labelled training flight"):
        make("cnn").fit(f, np.full(len(f), -1))
    with pytest.raises(ValueError, match="needs labels"):
        make("svm").fit(f)
