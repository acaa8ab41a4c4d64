"""QUADFormer: attention, loss terms, alarm rule, streaming, onsets and types."""

import math

import numpy as np
import pandas as pd
import pytest
import torch

from quadformer.detectors import load, make
from quadformer.detectors.context import Context
from quadformer.detectors.neural.quadformer import CLASSES, kth_of_last_n
from quadformer.detectors.neural.quadformer_net import QUADFormerNet, TwoBranchAttention, discrepancy, symmetric_kl
from quadformer.detectors.windows import Windows

TINY = {"window": 48, "fine": 16, "patch": 8, "d_model": 16, "heads": 2, "layers": 2, "epochs": 2, "steps_per_epoch": 5, "batch_size": 32}


def test_symmetric_kl_hand_case():
    p = torch.tensor([0.5, 0.5])
    q = torch.tensor([0.9, 0.1])
    expected = 0.4 * math.log(0.9 / 0.5) + 0.4 * math.log(0.5 / 0.1)
    assert symmetric_kl(p, q).item() == pytest.approx(expected, rel=1e-6)
    assert symmetric_kl(p, p).item() == pytest.approx(0.0, abs=1e-7)


def test_prior_is_a_normalised_gaussian_of_distance():
    torch.manual_seed(0)
    att = TwoBranchAttention(d_model=8, heads=2, positions=torch.arange(6.0))
    _, series, prior = att(torch.randn(3, 6, 8))
    assert torch.allclose(prior.sum(-1), torch.ones(3, 2, 6))
    assert torch.allclose(series.sum(-1), torch.ones(3, 2, 6))
    row = prior[0, 0, 2]                      # position 2: symmetric about it, peaked at it
    assert row.argmax().item() == 2
    assert torch.allclose(row[1], row[3]) and torch.allclose(row[0], row[4])


def test_minimax_gradients_descend_for_prior_and_ascend_for_series():
    s_logit = torch.randn(1, 1, 4, 4, requires_grad=True)
    p_logit = torch.randn(1, 1, 4, 4, requires_grad=True)
    both = discrepancy([s_logit.softmax(-1)], [p_logit.softmax(-1)]).sum()
    gs, gp = torch.autograd.grad(both, [s_logit, p_logit])
    mm = discrepancy([s_logit.softmax(-1)], [p_logit.softmax(-1)], "minimax").sum()
    ms, mp = torch.autograd.grad(mm, [s_logit, p_logit])
    assert mm.item() == pytest.approx(both.item())
    assert torch.allclose(mp, gp)          # prior: minimise the discrepancy
    assert torch.allclose(ms, -gs)         # series: maximise it


def test_last_position_scoring_equals_full_forward():
    torch.manual_seed(1)
    net = QUADFormerNet(5, len(CLASSES), Context(28, fine=12, patch=4), d_model=16, heads=2, layers=2).eval()
    x = torch.randn(4, 28, 5)
    with torch.no_grad():
        full, last = net(x), net(x, last_only=True)
    for k in ("recon", "logits"):
        assert torch.allclose(full[k][:, -1], last[k][:, -1], atol=1e-6)
    assert torch.allclose(discrepancy(full["series"], full["priors"])[:, -1],
                          discrepancy(last["series"], last["priors"])[:, -1], atol=1e-6)


@pytest.mark.parametrize("layers, use_prior, prior_sigma, context", [
    (2, True, None, Context(28, fine=12, patch=4)),
    (1, True, None, Context(28, fine=12, patch=4)),
    (3, True, 2.0, Context(28, fine=12, patch=4)),
    (2, False, None, Context(12, fine=12)),
])
def test_step_projections_score_as_the_network(layers, use_prior, prior_sigma, context):
    """``StepNet`` (the network from per-step projections: embedding and first-layer q, k, v of
    each step computed once, tokens as means of them) gives the score ingredients of the
    network's own forward on whole windows, in every configuration (depth, learned, fixed or
    no prior, with or without patches), offline (batches of windows in any order, the fused
    attention kernel) and one step at a time (the window's state of step embeddings, the
    explicit attention). Tolerance 1e-5 relative and absolute (float32, sums in another
    order)."""
    from quadformer.detectors.context import StepTokens
    from quadformer.detectors.neural.quadformer import last_step_parts
    from quadformer.detectors.neural.quadformer_steps import StepNet, projected_batches
    from quadformer.detectors.windows import Normalizer

    torch.manual_seed(layers)
    net = QUADFormerNet(5, len(CLASSES), context, d_model=16, heads=2, layers=layers, use_prior=use_prior,
                        prior_sigma=prior_sigma).eval()
    X = pd.DataFrame(np.random.default_rng(0).normal(size=(70, 5)), columns=[f"res_{i}" for i in range(5)])
    X.insert(0, "flight_id", np.repeat([0, 1], [30, 40]))
    win = Windows(X, list(X.columns[1:]), Normalizer().fit(X.iloc[:, 1:].to_numpy()), context.window)
    idx = np.arange(len(win))
    with torch.no_grad():
        ref = last_step_parts(net, torch.from_numpy(win[idx]), use_prior)
        steps = StepNet(net, use_prior)
        got = {k: torch.empty_like(v) for k, v in ref.items()}
        for pos, tokens, last in projected_batches(steps, win, idx[::-1], context, batch=16):
            for k, v in steps.score(tokens, last).items():
                got[k][torch.from_numpy(idx[::-1][pos].copy())] = v
        for k in ref:
            torch.testing.assert_close(got[k], ref[k], rtol=1e-5, atol=1e-5)
        online = StepTokens(context, 1, steps.width)
        for i in range(len(idx)):
            if i == 30:                              # the second flight starts from padding
                online = StepTokens(context, 1, steps.width)
            step = steps(torch.from_numpy(win[[i]][:, -1]), torch.from_numpy(online.context()))
            online.push(step.pop("embedding").numpy())
            for k in ref:
                torch.testing.assert_close(step[k], ref[k][i:i + 1], rtol=1e-5, atol=1e-5)


def test_k_of_n_rule():
    rng = np.random.default_rng(0)
    raw = rng.standard_normal(50)
    X = pd.DataFrame({"flight_id": np.repeat([0, 1], 25)})
    thr = 0.3
    for k, n in ((1, 1), (2, 3), (3, 5)):
        dec = kth_of_last_n(raw, X, k, n)
        for f in (0, 1):
            r = raw[25 * f:25 * (f + 1)]
            for i in range(25):
                window = r[max(0, i - n + 1):i + 1]
                assert (dec[25 * f + i] > thr) == ((window > thr).sum() >= k)


@pytest.fixture(scope="module")
def fitted(bias_dataset):
    f = bias_dataset.flights
    train = f[f.flight_id < 4].reset_index(drop=True)
    det = make("quadformer", **TINY).fit(train, train.label.to_numpy())
    det.calibrate(float(np.percentile(det.decision_function(train), 80)))
    return det, f[f.flight_id >= 4].reset_index(drop=True)


def test_streaming_matches_offline(fitted):
    det, test = fitted
    flight = test[test.flight_id == 4].reset_index(drop=True)
    offline = det.decision_function(flight)
    alarms = offline > det.threshold_
    types = det.predict_type(flight)
    stream = det.stream()
    steps = [stream.update(row) for row in flight[det.features_].to_dict("records")]
    score = np.array([s.score[0] for s in steps])
    # float32 network, one window at a time online vs batches offline: scores agree to 1e-5;
    # alarms and types are identical
    assert np.allclose(score, offline, rtol=1e-5, atol=1e-5)
    assert np.array_equal(np.array([s.alarm[0] for s in steps]), alarms)
    assert [s.attack_type[0] for s in steps] == list(types)
    with pytest.raises(ValueError, match="finite values"):
        det.stream().update(np.full(len(det.features_), np.nan))


def test_step_scoring_equals_the_network_on_whole_windows(fitted):
    """Offline scoring (``raw_scores``, from per-step projections over batches of windows) and
    the online stream (one GPS step of every flight at a time, the state of the window carried
    from step to step) give the scores and attack types of the network run on each step's whole
    window (``score_windows``, the full recomputation): scores to 1e-4, relative and absolute
    (float32 network, sums in another order), types equal."""
    det, test = fitted
    win = Windows(test, det.features_, det.normalizer_, det.window)
    full_raw, full_types = det.score_windows(win[np.arange(len(win))])
    det.clear_cache()
    raw, types = det.raw_scores(test)
    np.testing.assert_allclose(raw, full_raw, rtol=1e-4, atol=1e-4)
    assert list(np.array(det.classes_, dtype=object)[types]) == list(full_types)
    full = kth_of_last_n(full_raw, test, det.k, det.n)
    ids = test.flight_id.unique()
    n_steps = len(test) // len(ids)
    cols = {c: test[c].to_numpy().reshape(len(ids), n_steps) for c in det.features_}
    stream = det.stream(len(ids))
    steps = [stream.update({c: v[:, j] for c, v in cols.items()}) for j in range(n_steps)]
    np.testing.assert_allclose(np.stack([s.score for s in steps], 1).reshape(-1), full, rtol=1e-4, atol=1e-4)
    assert list(np.stack([s.attack_type for s in steps], 1).reshape(-1)) == list(full_types)


def test_onsets_and_types_of_every_alarm_run(fitted):
    det, test = fitted
    s = det.decision_function(test)
    alarms = s > det.threshold_
    starts = [(fid, t) for fid, g in test.assign(a=alarms).groupby("flight_id", sort=False)
              for t in g.t.to_numpy()[g.a.to_numpy() & ~np.r_[False, g.a.to_numpy()[:-1]]]]
    assert len(starts) >= 2                       # the fitted threshold (80th percentile) alarms
    onsets = det.onset_times(test, alarms)
    assert [(f, ta) for f, ta, _ in onsets] == starts
    raw, _ = det.raw_scores(test)
    for fid, t_alarm, t_onset in onsets:
        g = test.flight_id.to_numpy() == fid
        t, r = test.t.to_numpy()[g], raw[g]
        assert t[0] <= t_onset <= t_alarm
        # every step from the onset to the alarm scored above the back-tracking level, the one
        # before the onset (if any) did not
        inside = (t >= t_onset) & (t < t_alarm)
        assert np.all(r[inside] > det._lower())
        before = np.nonzero(t < t_onset)[0]
        assert before.size == 0 or r[before[-1]] <= det._lower()
    assert set(det.predict_type(test)) <= set(CLASSES[1:]) and det.classes_ == list(CLASSES)


def test_alerts_carry_quadformer_onsets_and_types(fitted):
    from quadformer.detectors import alerts_from_scores

    det, test = fitted
    s = det.decision_function(test)
    alerts = alerts_from_scores(test, s, det)
    onsets = det.onset_times(test, s > det.threshold_)
    types = det.predict_type(test)
    assert len(alerts) == len(onsets) >= 2
    for a, (fid, t_alarm, t_onset) in zip(alerts, onsets):
        assert (a.flight_id, a.start_s, a.onset_s) == (fid, t_alarm, t_onset)
        row = np.nonzero((test.flight_id.to_numpy() == fid) & (test.t.to_numpy() == t_alarm))[0][0]
        assert a.attack_type == types[row] and a.attack_type in CLASSES[1:]
        assert a.score > det.threshold_


def test_checkpoint_round_trip_and_variants(fitted, tmp_path):
    det, test = fitted
    back = load(det.save(tmp_path / "qf.json"))
    assert np.array_equal(back.decision_function(test), det.decision_function(test))
    assert back.threshold_ == det.threshold_
    nosup = make("quadformer-nosup", **TINY)
    assert not nosup.supervised and "supervised" not in nosup.get_params()
    noprior = make("quadformer-noprior")
    assert noprior.use_prior is True and noprior.prior_sigma == 2.0 and noprior._disc
    assert "prior_sigma" not in noprior.get_params()
    assert make("quadformer-nodisc").use_discrepancy is False


def test_fixed_prior_is_a_gaussian_of_fixed_width():
    """quadformer-noprior's prior: a Gaussian kernel of width 2 steps, whatever the input."""
    torch.manual_seed(0)
    att = TwoBranchAttention(d_model=8, heads=2, positions=torch.arange(6.0), prior_sigma=2.0)
    assert att.sigma is None
    _, _, prior = att(torch.randn(3, 6, 8))
    d = torch.arange(6.0)
    want = torch.softmax(-(d[:, None] - d[None, :]) ** 2 / (2 * 2.0 ** 2), dim=-1)
    assert torch.allclose(prior, want.expand(3, 2, 6, 6), atol=1e-7)
    _, _, last = att(torch.randn(3, 6, 8), last_row=True)
    assert torch.allclose(last[:, :, 0], want[-1].expand(3, 2, 6), atol=1e-7)


def test_noprior_and_nodisc_train_different_networks(bias_dataset):
    """With a fixed prior the discrepancy still exists: noprior keeps the discrepancy term in
    its loss and score, nodisc drops it, so the two variants differ (they used to train the
    same network)."""
    f = bias_dataset.flights
    train = f[f.flight_id < 4].reset_index(drop=True)
    test = f[f.flight_id >= 4].reset_index(drop=True)
    y = train.label.to_numpy()
    noprior = make("quadformer-noprior", **TINY).fit(train, y)
    nodisc = make("quadformer-nodisc", **TINY).fit(train, y)
    parts = noprior._parts(Windows(test, noprior.features_, noprior.normalizer_, noprior.window),
                           np.arange(len(test)))
    assert np.all(parts["dis"] > 0) and noprior.dis_scale_ != 1.0     # a discrepancy is computed
    assert nodisc.dis_scale_ == 1.0
    assert not np.allclose(noprior.decision_function(test), nodisc.decision_function(test))
    assert [h["train_loss"] for h in noprior.history_] != [h["train_loss"] for h in nodisc.history_]


def test_alarm_rule_variants_share_one_scoring_of_the_network(bias_dataset):
    f = bias_dataset.flights
    train, val = f[f.flight_id < 4].reset_index(drop=True), f[f.flight_id >= 4].reset_index(drop=True)
    det = make("quadformer", **TINY).fit(train, train.label.to_numpy())
    variants = [det.with_post(k=k, n=n, w_anomaly=w) for k, n, w in ((1, 3, 1.0), (2, 5, 0.0), (3, 5, 1.0))]
    first = variants[0].raw_scores(val)
    parts = det.__dict__["_cache"]["parts"]          # the network's output, computed once
    for v in variants[1:]:
        v.decision_function(val)
        assert v.__dict__["_cache"]["parts"] is parts
    # the variants still differ where their parameters say: the score weight and the k-of-n rule
    assert not np.array_equal(variants[1].raw_scores(val)[0], first[0])
    assert not np.array_equal(variants[1].decision_function(val), variants[2].decision_function(val))
    # scores on other flights replace the cached ingredients for every variant
    variants[2].raw_scores(train)
    assert det.__dict__["_cache"]["parts"] is not parts


def test_the_online_step_raises_the_offline_alerts_with_their_onsets(fitted):
    """The online step (one GPS step of every test flight at a time, as the closed loop and the
    monitor drive it) gives the alerts that offline scoring gives: same flights, start, estimated
    onset (from the stream's onset flags), type and end; peak scores to the stream's float32
    agreement."""
    from quadformer.detectors import alerts_from_scores
    from quadformer.resilience.step import OnlineStep

    det, test = fitted
    offline = alerts_from_scores(test, det.decision_function(test), det)
    groups = [g for _, g in test.groupby("flight_id", sort=False)]
    assert len({len(g) for g in groups}) == 1
    step = OnlineStep(det.stream(len(groups)), flight_ids=[g.flight_id.iloc[0] for g in groups])
    events = []
    for j in range(len(groups[0])):
        rows = {c: np.array([g[c].iloc[j] for g in groups]) for c in det.features_}
        t = np.array([g.t.iloc[j] for g in groups])
        events += step.update(t, _groups(rows)).events
    events += step.finish()
    live = step.alerts
    assert len(live) == len(offline) >= 2
    assert any(a.onset_s < a.start_s for a in live)          # onsets estimated before the alarm
    for a, b in zip(live, offline):
        assert (a.flight_id, a.start_s, a.onset_s, a.attack_type, a.end_s) == \
               (b.flight_id, b.start_s, b.onset_s, b.attack_type, b.end_s)
        assert a.score == pytest.approx(b.score, rel=1e-5, abs=1e-5)
    assert sum(e.event == "alert_start" for e in events) == sum(e.event == "alert_end" for e in events) == len(live)


def _groups(cols: dict) -> dict:
    """Columns -> the residue groups they belong to ((n, width) arrays), as a residue stream gives them."""
    from quadformer.estimator.schema import GROUPS

    out = {}
    for g in GROUPS.values():
        if all(c in cols for c in g.columns):
            out[g.name] = np.stack([cols[c] for c in g.columns], axis=1)
    return out
