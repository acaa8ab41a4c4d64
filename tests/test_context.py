"""Long context: windows summarised into tokens (``detectors.context``), shared by every
window detector, offline, online and in the networks."""

import numpy as np
import pandas as pd
import pytest
import torch

from quadformer.detectors import make
from quadformer.detectors.context import FINE, PATCH, WINDOW, Context
from quadformer.detectors.neural.quadformer_net import QUADFormerNet
from quadformer.estimator.schema import DETECTOR_FEATURES


def test_tokens_by_hand_numpy_and_torch_agree():
    # 10 steps: two patches of 4 (steps 0-3, 4-7), then 2 steps one by one
    c = Context(10, fine=2, patch=4)
    x = np.stack([np.arange(10.0), 10 * np.arange(10.0)], axis=-1)[None].astype(np.float32)   # (1, 10, 2)
    want = np.array([[[1.5, 15.0], [5.5, 55.0], [8.0, 80.0], [9.0, 90.0]]], dtype=np.float32)
    assert c.n_patches == 2 and c.n_tokens == 4
    np.testing.assert_array_equal(c.tokens(x), want)
    np.testing.assert_array_equal(c.tokens(torch.from_numpy(x)).numpy(), want)
    # token centres in steps from the window's first step
    np.testing.assert_array_equal(c.positions(), [1.5, 5.5, 8.0, 9.0])


def test_defaults_span_32_seconds_in_50_tokens():
    c = Context(WINDOW, FINE, PATCH)
    assert (c.window, c.fine, c.patch) == (320, 32, 16)
    assert c.n_tokens == 18 + 32
    pos = c.positions()
    assert pos[0] == 7.5 and pos[-1] == 319.0 and np.all(np.diff(pos) > 0)


def test_a_window_no_longer_than_fine_is_a_plain_window():
    """A model saved with a 32-step window (before tokens) builds the same network."""
    c = Context(32)
    x = np.random.default_rng(0).normal(size=(3, 32, 5)).astype(np.float32)
    assert c.fine == 32 and c.n_patches == 0 and c.tokens(x) is x
    np.testing.assert_array_equal(c.positions(), np.arange(32.0))
    net = QUADFormerNet(5, 3, c, d_model=16, heads=2, layers=1)
    assert net.pe.shape == (32, 16)


def test_bad_contexts_are_named():
    with pytest.raises(ValueError, match="multiple of patch"):
        Context(100, fine=32, patch=16)
    with pytest.raises(ValueError, match="window must be at least 1"):
        Context(0)
    with pytest.raises(ValueError, match="fine and patch"):
        Context(64, fine=32, patch=0)
    with pytest.raises(ValueError, match="windows of 40 steps given to a context of 48"):
        Context(48, fine=16, patch=8).tokens(np.zeros((1, 40, 2), dtype=np.float32))
    # a detector checks its context before any work
    X = _residues(np.random.default_rng(0), flights=1, steps=50)
    for method in ("pca", "svm", "cnn", "quadformer"):
        with pytest.raises(ValueError, match="multiple of patch"):
            make(method, window=100).fit(X, X["label"].to_numpy())


def _residues(rng, flights: int, steps: int) -> pd.DataFrame:
    """Residue-shaped frames (every detector feature), white noise, all labelled clean."""
    frames = []
    for f in range(flights):
        d = pd.DataFrame(rng.normal(size=(steps, len(DETECTOR_FEATURES))), columns=list(DETECTOR_FEATURES))
        d.insert(0, "flight_id", f)
        d.insert(1, "t", np.arange(steps) * 0.1)
        d["label"] = 0
        frames.append(d)
    return pd.concat(frames, ignore_index=True)


@pytest.fixture(scope="module")
def pca_default():
    """A PCA anchor with the default 320-step context, fitted on noise."""
    rng = np.random.default_rng(5)
    X = _residues(rng, flights=3, steps=400)
    return make("pca", n_components=8, max_windows=1000).fit(X, X["label"].to_numpy()), _residues(rng, 1, 400)


def test_default_context_reaches_back_320_steps_and_no_further(pca_default):
    det, flight = pca_default
    t = 380
    base = det.decision_function(flight)[t]
    for back, reaches in ((0, True), (31, True), (100, True), (319, True), (320, False), (350, False)):
        hit = flight.copy()
        hit.loc[t - back, DETECTOR_FEATURES[0]] += 50.0
        changed = det.decision_function(hit)[t] != base
        assert changed == reaches, f"a step {back} steps back {'should' if reaches else 'should not'} change the score"


def test_default_context_stream_equals_offline(pca_default):
    det, flight = pca_default
    det.calibrate(float(np.quantile(det.decision_function(flight), 0.9)))
    offline = det.decision_function(flight)
    s = det.stream(1)
    online = np.array([s.update(flight[list(det.features_)].to_numpy()[i:i + 1]).score[0]
                       for i in range(len(flight))])
    # the same windows through the same tokens: equal up to float32 rounding of the batch
    np.testing.assert_allclose(online, offline, rtol=1e-5, atol=1e-6)


def test_tokens_of_indexed_windows_equal_the_tokens_of_gathered_windows():
    """``Windows.tokens`` (patch means computed once, offline scoring) gives exactly the tokens of
    the gathered windows, padding included, across flights."""
    from quadformer.detectors.windows import Normalizer, Windows

    rng = np.random.default_rng(2)
    X = pd.concat([_residues(rng, 1, n).assign(flight_id=i) for i, n in enumerate((30, 70, 5))], ignore_index=True)
    feats = list(DETECTOR_FEATURES)
    win = Windows(X, feats, Normalizer().fit(X[feats].to_numpy()), 48)
    idx = np.arange(len(win))
    for c in (Context(48, fine=16, patch=8), Context(48, fine=48), Context(48, fine=8, patch=4)):
        np.testing.assert_array_equal(win.tokens(idx, c), c.tokens(win[idx]))
    with pytest.raises(ValueError, match="a context of 320 steps for windows of 48"):
        win.tokens(idx, Context(320))


def test_step_tokens_one_step_at_a_time_equal_the_tokens_of_whole_windows():
    """``StepTokens`` (the last ``fine`` vectors and the float64 prefix sums of the last
    ``window``) gives, before each step, the tokens of the window ending at that step less its
    last one: those of the gathered window, zero padding before the flight's start included,
    for several flights at once, long past the first wrap of its rings (float32 rounding of the
    float64 means: to 1e-6)."""
    from quadformer.detectors.context import StepTokens

    rng = np.random.default_rng(4)
    for c in (Context(48, fine=16, patch=8), Context(48, fine=48), Context(48, fine=1, patch=1), Context(320)):
        v = rng.normal(size=(2, 400, 3)).astype(np.float32) * 10
        padded = np.concatenate([np.zeros((2, c.window - 1, 3), np.float32), v], axis=1)
        st = StepTokens(c, 2, 3)
        for k in range(v.shape[1]):
            want = c.tokens(padded[:, k:k + c.window])
            np.testing.assert_allclose(st.context(), want[:, :-1], rtol=1e-6, atol=1e-6)
            st.push(v[:, k])


def test_window_spans_cover_each_window_once_in_short_runs_of_rows():
    from quadformer.detectors.windows import Normalizer, Windows

    rng = np.random.default_rng(6)
    X = pd.concat([_residues(rng, 1, n).assign(flight_id=i) for i, n in enumerate((30, 70, 5))], ignore_index=True)
    feats = list(DETECTOR_FEATURES)
    win = Windows(X, feats, Normalizer().fit(X[feats].to_numpy()), 16)
    idx = rng.permutation(len(win))[:60]
    seen = []
    for pos, rows, starts in win.spans(idx, 40):
        assert len(rows) <= 40 and np.all(np.diff(starts) >= 0)
        for p, s in zip(pos, starts):
            np.testing.assert_array_equal(rows[s:s + 16], win[idx[[p]]][0])
        seen += list(pos)
    assert sorted(seen) == list(range(len(idx)))
