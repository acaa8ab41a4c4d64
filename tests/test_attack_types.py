"""Attack typing by shape fitting: each kind on a flight built by hand, simulated flights, alerts."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from quadformer.detectors import ShapeTyper, alerts_from_scores
from quadformer.detectors.attack_types import TYPING_COLUMNS, UNTYPED, alert_typer
from quadformer.detectors.reference_rows import Unanchored
from quadformer.estimator.schema import ATTACK_TYPES, columns
from shapes_support import circle

RATE = 10.0
ONSET = 15.0


def flight(kind: str, seed: int = 0, duration: float = 40.0, onset: float = ONSET, rate: float = 0.5,
           follows: bool = False) -> pd.DataFrame:
    """One flight's typing columns, built as the reference residues are: a vehicle on a circle
    (r 5 m, 0.3 rad/s), GPS = truth + white noise (0.3 m, 0.05 m/s) + the attack, a reference =
    truth + a slow drift; their difference smoothed (1 s), minus an anchor 3 s behind that
    freezes at the onset (``follows``: goes on following, as it does for a drift too slow to
    disagree), and whitened by a constant stated std. ``rate``: a ramp's, m/s."""
    rng, t, p, v, fix = circle(seed, duration, RATE)
    honest = fix.copy()
    on = t >= onset
    tau = np.where(on, t - onset, 0.0)
    u = np.array([0.6, 0.8, 0.0])
    k0 = int(round(onset * RATE))
    if kind == "bias":
        fix[on, :3] += 3.0 * u
    elif kind == "ramp":
        fix[on, :3] += (rate * tau[on])[:, None] * u
        fix[on, 3:] += rate * u
    elif kind == "sinusoid":
        f = 0.15
        fix[on, :3] += (3.0 * np.sin(2 * np.pi * f * tau[on]))[:, None] * u
        fix[on, 3:] += (3.0 * 2 * np.pi * f * np.cos(2 * np.pi * f * tau[on]))[:, None] * u
    elif kind == "intermittent":
        fix[on & (np.mod(tau, 4.0) < 2.0), :3] += 3.0 * u
    elif kind == "replay":
        src = np.arange(len(t)) - int(6.0 * RATE)
        fix[on] = honest[src[on]]
    elif kind == "freeze":
        fix[on] = honest[k0 - 1]
    ref = np.concatenate([p + 0.02 * t[:, None], v], 1)
    raw = fix - ref
    alpha = 1.0 - np.exp(-1.0 / RATE)
    a = np.empty_like(raw)
    a[0] = raw[0]
    for i in range(1, len(t)):
        a[i] = a[i - 1] + alpha * (raw[i] - a[i - 1])
    lag = int(3 * RATE)
    frozen_at = len(t) if follows else k0
    anchor = np.array([a[max(min(i, frozen_at) - lag, 0)] for i in range(len(t))])
    age = np.where(on & ~follows, t - onset + 3.0, 3.0)
    X = pd.DataFrame({"flight_id": seed, "t": t, "res_ref_age": age})
    stated = [0.3, 0.3, 0.3, 0.05, 0.05, 0.05]          # the std the reference states (whitening)
    for i, (c, cw) in enumerate(zip(columns("res_ref_d"), columns("res_ref_w"))):
        X[c] = a[:, i] - anchor[:, i]
        X[cw] = X[c] / stated[i]
    for i, c in enumerate(columns("gps_vel")):
        X[c] = fix[:, 3 + i]
    return X


@pytest.mark.parametrize("kind", ATTACK_TYPES)
def test_each_kind_is_typed_from_its_shape(kind):
    typer = ShapeTyper()
    right = 0
    for seed in range(3):
        X = flight(kind, seed)
        k = int((ONSET + 8.0) * RATE)
        got, costs = typer.type_at(typer.prepare(X), k)
        assert set(costs) == set(ATTACK_TYPES) and all(np.isfinite(list(costs.values())))
        right += got == kind
    assert right == 3, f"{kind}: typed right on {right} of 3 flights"


def test_an_onset_between_the_grid_onsets_is_found_at_its_row():
    # a step switched on at 15.2 s, between the 0.5-s grid's onsets: the onset is refined to the spoof's
    # first fix at every row typed (one or two rows off, the step is mostly left unexplained)
    typer = ShapeTyper()
    for kind, rate in (("bias", 0.5), ("ramp", 3.0)):
        f = typer.prepare(flight(kind, 0, onset=15.2, rate=rate))
        for k in range(int(18.2 * RATE), int(23.2 * RATE), 3):
            typed = typer.fit_at(f, k)
            assert (typed.kind, typed.onset) == (kind, pytest.approx(15.2)), (kind, k)


def test_before_the_first_switch_an_intermittent_spoof_is_a_bias():
    # 1.5 s after the onset an intermittent spoof (on for 2 s of every 4) has not switched yet
    typer = ShapeTyper()
    X = flight("intermittent", 0)
    assert typer.type_at(typer.prepare(X), int((ONSET + 1.5) * RATE))[0] == "bias"
    assert typer.type_at(typer.prepare(X), int((ONSET + 9.0) * RATE))[0] == "intermittent"


def test_a_drift_too_slow_to_freeze_the_anchor_is_typed_ramp():
    # 0.1 m/s: the anchor follows it 3 s behind, so the anchored difference holds 0.3 m and no
    # velocity; the velocity without the anchor keeps the drift's 0.1 m/s from its onset
    typer = ShapeTyper()
    for seed in range(3):
        X = flight("ramp", seed, rate=0.1, follows=True)
        assert X.res_ref_age.max() == 3.0
        f = typer.prepare(X)
        assert f.dv[int((ONSET + 2) * RATE):, :2].mean(0) - f.dv[:int(ONSET * RATE), :2].mean(0) == \
            pytest.approx([0.06, 0.08], abs=0.02)     # 4 std of the two means
        assert typer.type_at(f, int((ONSET + 10.0) * RATE))[0] == "ramp"
    # the same flight without the drift: no velocity step, typed as nothing but noise would be
    clean = typer.prepare(flight("bias", 0, onset=1e9, follows=True))
    assert np.abs(clean.dv[50:, :2].mean(0) - clean.dv[50:150, :2].mean(0)).max() < 0.02


def test_streaming_rows_give_the_unanchored_difference_of_the_whole_flight():
    # a bounded history (the live monitor's) with Unanchored carried over every row equals the
    # arrays prepared from the whole flight
    typer = ShapeTyper()
    X = flight("ramp", 2, rate=0.1, follows=True)
    u = Unanchored(step=1.0 / RATE)
    pushed = [u.push(r, age) for r, age in zip(X[columns("res_ref_d")].to_numpy(), X.res_ref_age.to_numpy())]
    a, j = (np.array(x) for x in zip(*pushed))
    whole = typer.prepare(X)
    keep = slice(len(X) - 300, len(X))
    part = typer.prepare(X.iloc[keep].reset_index(drop=True), unanchored=a[keep])
    np.testing.assert_allclose(part.dv[1:], whole.dv[keep][1:], atol=1e-9)
    np.testing.assert_allclose(part.dp[1:], whole.dp[keep][1:], atol=1e-9)
    # the same type (the white noise is estimated from the rows at hand: costs differ slightly)
    assert typer.type_at(part, 299)[0] == typer.type_at(whole, len(X) - 1)[0] == "ramp"


def test_the_type_uses_the_flight_up_to_the_step_typed_only():
    typer = ShapeTyper()
    X = flight("ramp", 1)
    k = int((ONSET + 6.0) * RATE)
    whole = typer.type_at(typer.prepare(X), k)
    cut = typer.type_at(typer.prepare(X.iloc[:k + 1]), k)
    assert whole[0] == cut[0] == "ramp"
    assert whole[1] == pytest.approx(cut[1], rel=1e-9)


def test_a_type_is_confirmed_five_seconds_later_within_its_flight():
    X = pd.concat([flight("ramp", 0, duration=25.0), flight("bias", 1, duration=25.0)], ignore_index=True)
    typer = ShapeTyper()
    rows = np.array([int((ONSET + 1.0) * RATE), 250 + 30, 250 + 230])
    got = typer.confirm_rows(X, rows)
    # 5 s later at 10 Hz; the last row of the second flight when it ends sooner
    assert list(got) == [rows[0] + 50, 330, 499]
    assert list(X.flight_id.iloc[got]) == [0, 1, 1]
    assert typer.type_rows(X, got[:1])[0] == "ramp"


def test_simulated_bias_attacks_are_typed_bias(bias_dataset):
    typer = ShapeTyper()
    f, sc = bias_dataset.flights, bias_dataset.scenarios
    attacked = sc[sc.attacked]
    assert len(attacked) >= 2
    rows = [int(np.flatnonzero((f.flight_id == s.flight_id).to_numpy() & (f.t.to_numpy() >= s.onset + 5.0))[0])
            for s in attacked.itertuples()]
    assert list(typer.type_rows(f, np.array(rows))) == ["bias"] * len(rows)


def test_alerts_take_the_typer_types(bias_dataset):
    f, sc = bias_dataset.flights, bias_dataset.scenarios
    score = f.label.to_numpy(dtype=float)          # an alarm exactly on the attacked steps
    typer = alert_typer(f)
    alerts = alerts_from_scores(f, score, threshold=0.5, typer=typer)
    assert len(alerts) == int(sc.attacked.sum())
    starts = np.flatnonzero(np.diff(np.concatenate([[0], f.label.to_numpy()])) == 1)
    assert [a.attack_type for a in alerts] == list(ShapeTyper().type_rows(f, starts))
    assert all(a.attack_type in ATTACK_TYPES for a in alerts)
    # each confirmed 5 s after its start: every one a bias, as the dataset's attacks are
    later = ShapeTyper().confirm_rows(f, starts)
    assert np.allclose(f.t.to_numpy()[later] - f.t.to_numpy()[starts], 5.0)
    assert [a.confirmed_type for a in alerts] == ["bias"] * len(alerts)
    assert "confirmed bias" in str(alerts[0])
    # without a typer an alert of a detector that does not classify says "attack", unconfirmed
    plain = alerts_from_scores(f, score, threshold=0.5)
    assert {a.attack_type for a in plain} == {"attack"} and {a.confirmed_type for a in plain} == {None}
    # detector typing, or rows without the typer's columns: no typer
    assert alert_typer(f, "detector") is None and alert_typer(f[["flight_id", "t"]]) is None


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="typing: unknown 'labels'"):
        alert_typer(pd.DataFrame(), "labels")
    with pytest.raises(ValueError, match="needs the columns res_ref_age"):
        ShapeTyper().prepare(flight("bias").drop(columns="res_ref_age"))
    with pytest.raises(ValueError, match="kinds: unknown \\['spoof'\\]"):
        ShapeTyper(kinds=("bias", "spoof"))
    with pytest.raises(ValueError, match="window must be > 0"):
        ShapeTyper(window=0.0)
    with pytest.raises(ValueError, match="delays"):
        ShapeTyper(delays=())
    # non-finite values in the window, or too short a flight: untyped, not a guess
    typer = ShapeTyper()
    X = flight("bias")
    k = int((ONSET + 5.0) * RATE)
    X.loc[k - 3, "res_ref_d_px"] = np.nan
    assert typer.type_at(typer.prepare(X), k) == (UNTYPED, {})
    assert typer.type_at(typer.prepare(X.iloc[:3]), 2) == (UNTYPED, {})
    assert set(TYPING_COLUMNS) <= set(flight("bias").columns)


def test_a_non_finite_row_leaves_the_rest_of_the_flight_typable():
    # one damaged row of residues: typed `attack` while it is in the window, the ramp afterwards
    typer = ShapeTyper(window=5.0)
    X = flight("ramp", 0)
    bad = int((ONSET - 3.0) * RATE)
    X.loc[bad, columns("res_ref_d")] = np.nan
    f = typer.prepare(X)
    assert typer.type_at(f, bad + 10)[0] == UNTYPED
    assert np.isfinite(f.dv[bad + 2:]).all()          # the row and the next (smoothing undone) only
    assert typer.type_at(f, int((ONSET + 4.0) * RATE))[0] == "ramp"


def test_a_receiver_slower_than_the_filter_rate_is_unsmoothed_at_the_filter_step():
    # a log's 5 Hz fixes under a filter at 10 Hz: the reference smooths and ages 0.1 s per fix
    # while the rows are 0.2 s apart; the raw differences come out the same as at 10 Hz
    typer = ShapeTyper()
    X = flight("bias", 1)
    slow = X.assign(t=X.t * 2.0)
    np.testing.assert_allclose(typer.prepare(slow).dp, typer.prepare(X).dp, atol=1e-9)
    assert typer.type_at(typer.prepare(slow), int((ONSET + 8.0) * RATE))[0] == "bias"
