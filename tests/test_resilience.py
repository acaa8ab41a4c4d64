"""Resilient estimation: alerts, detector streams, and the policies in closed loop on small real
flights (the admission rules on hand-made streams: test_admission.py)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import torch
from test_admission import _drive
from typer.testing import CliRunner

from quadformer.cli import app
from quadformer.config import AttackConfig, SimConfig
from quadformer.detectors import make
from quadformer.evaluation.protocol import best_f1_threshold
from quadformer.detectors import StreamGroup, alerts_from_scores
from quadformer.evaluation.resilience import flight_metrics
from quadformer.resilience import POLICIES, Admission, AdmissionConfig, AdmissionGroup
from quadformer.simulation.closed_loop import simulate_groups


def test_alerts_from_hand_made_scores():
    X = pd.DataFrame({"flight_id": [7] * 10 + [8] * 5, "t": np.r_[np.arange(10), np.arange(5)] * 0.1})
    s = np.array([0, 0, 5, 6, 0, 0, 0, 9, 9, 9, 0, 0, 0, 0, 0], dtype=float)
    alerts = alerts_from_scores(X, s, threshold=1.0)
    assert [(a.flight_id, a.start_s, a.end_s, a.score) for a in alerts] == [
        (7, pytest.approx(0.2), pytest.approx(0.4), 6.0), (7, pytest.approx(0.7), None, 9.0)]
    assert alerts[0].onset_s == alerts[0].start_s and alerts[0].attack_type == "attack"
    with pytest.raises(ValueError, match="scores for 15 rows"):
        alerts_from_scores(X, s[:-1], threshold=1.0)


# The closed-loop runs of this file, flown together in one batch of 24 s flights (the simulator's
# time goes with the flights' length, hardly with their number; each configuration's flights
# are those it flies alone, bit for bit):
# - "loop": the 6 flights of the bias dataset flown again under every policy (CUSUM drives the
#   resilient one);
# - "main", "no_rollback", "no_blend": one flight with a 15 m bias on x from 6 s to 16 s, flown
#   by the resilient policy (BHT driving it) and by the PX4-like gate, and again with the
#   rollback or the blend switched off;
# - "stale": two flights flown by the resilient policy with the CUSUM, whose statistic keeps the
#   attack's memory for minutes after a spoof: flight 172 draws a 3.7 m bias, mostly on x, from
#   2.5 s to 7.9 s, flight 7 a 0.27 m/s drift on x from 2.5 s to the end (in 15 s flights flight
#   25 drew a bias like 172's: a flight's draws depend on the flights' length).
_JUMP = SimConfig(model="I", noise="gaussian", flights=1, duration=24.0, seed=2,
                  attack=AttackConfig(kind="bias", fraction=1.0, onset=(6.0, 6.0), duration=(10.0, 10.0),
                                      magnitude=(15.0, 15.0), axes="x"))
_STALE = SimConfig(model="I", noise="gaussian", flights=1, duration=24.0, seed=2,
                   attack=AttackConfig(kind="mix", mix=("bias", "ramp"), fraction=1.0, onset=(2.5, 2.5),
                                       duration=(3.0, 30.0), magnitude=(3.0, 5.0), rate=(0.2, 0.4)))


@pytest.fixture(scope="module")
def flown(bias_dataset):
    cfg = bias_dataset.config
    f = bias_dataset.flights
    cusum = make("cusum").fit(f, f.label.to_numpy())
    s = cusum.decision_function(f)
    cusum.calibrate(best_f1_threshold(s, f.label.to_numpy())[0])
    bht = make("bht", inflation=3.0).fit(f, f.label.to_numpy()).calibrate(0.0)   # posterior above 1/2
    att = bias_dataset.scenarios.attacked.to_numpy(bool)
    P = len(POLICIES)
    loop = (cfg, np.tile(np.arange(6), P), np.tile(att, P), Admission(np.repeat(POLICIES, 6), 10.0))
    # the three jump runs, each under its own admission configuration
    jump = [Admission(["resilient", "px4"], 10.0), Admission(["resilient"], 10.0, AdmissionConfig(rollback_s=0.0)),
            Admission(["resilient"], 10.0, AdmissionConfig(blend_s=0.0))]
    jump = [(_JUMP, np.zeros(len(a.policies), int), np.ones(len(a.policies), bool), a) for a in jump]
    stale = (_STALE, np.array([172, 7]), np.ones(2, bool), Admission(["resilient"] * 2, 10.0))
    runs = [loop, *jump, stale]
    stream = StreamGroup([cusum.stream(6 * P), bht.stream(4), cusum.stream(2)])
    r = simulate_groups([g[:3] for g in runs], admission=AdmissionGroup([g[3] for g in runs]), stream=stream)
    return {**dict(zip(("loop", "main", "no_rollback", "no_blend", "stale"), r)), "offline": s.reshape(6, -1),
            "att": att}


@pytest.fixture(scope="module")
def loop(flown):
    return {"r": flown["loop"], "offline": flown["offline"], "att": flown["att"]}


def _rows(loop, policy):
    return np.arange(6) + 6 * POLICIES.index(policy)


def test_naive_policy_reproduces_the_dataset_and_online_scores_match(loop, bias_dataset):
    r = loop["r"]
    naive = _rows(loop, "naive")
    est = bias_dataset.flights[["est_pos_x", "est_pos_y", "est_pos_z"]].to_numpy().reshape(6, -1, 3)
    np.testing.assert_array_equal(r["est_pos"][naive], est)
    np.testing.assert_array_equal(r["admission"]["score"][naive], loop["offline"])
    assert r["admission"]["fused"][naive].all()


def test_oracle_keeps_the_vehicle_on_its_mission_while_naive_follows_the_spoof(loop, bias_dataset):
    r = loop["r"]
    mags = bias_dataset.scenarios.magnitude.to_numpy()
    clean_dev = [flight_metrics(r["t"], r["label"][b], r["true_pos"][b], r["est_pos"][b], r["ref_pos"][b],
                                r["admission"]["fused"][b])["max_dev_flight_m"]
                 for b in _rows(loop, "naive")[~loop["att"]]]
    for i in np.nonzero(loop["att"])[0]:
        m = {p: flight_metrics(r["t"], r["label"][b], r["true_pos"][b], r["est_pos"][b], r["ref_pos"][b],
                               r["admission"]["fused"][b]) for p in POLICIES for b in [_rows(loop, p)[i]]}
        # the oracle's deviation stays at the level of clean flights (VIO drift, wind, GPS
        # noise fused before the attack); the naive vehicle is dragged towards the offset (in
        # these 6-10 s attacks the filter absorbs it over seconds and the controller's bounded
        # setpoint error limits the pace, so not all the way)
        assert m["oracle"]["max_dev_m"] <= max(clean_dev) + 0.3, (i, m["oracle"], clean_dev)
        assert m["naive"]["max_dev_m"] >= max(0.3 * mags[i], m["oracle"]["max_dev_m"] + 0.5), (i, m, mags[i])
        assert m["oracle"]["readmit_delay_s"] == 0.0 and m["oracle"]["exclusion_delay_s"] == 0.0
        # the detector-driven policy excluded GPS within 1 s of the onset
        assert m["resilient"]["exclusion_delay_s"] is not None and m["resilient"]["exclusion_delay_s"] <= 1.0
        assert m["resilient"]["max_dev_m"] < m["naive"]["max_dev_m"]


def test_readmission_in_the_loop_does_not_jump(loop):
    r = loop["r"]
    for b in _rows(loop, "oracle")[loop["att"]]:
        end = np.nonzero(r["label"][b])[0][-1] + 1            # first honest fix: re-admitted
        err = r["est_pos"][b] - r["true_pos"][b]
        step = np.linalg.norm(np.diff(err[end - 1:end + 30], axis=0), axis=1)
        assert step.max() < 0.05, step.max()                  # m per GPS step


def test_readmission_blend_spreads_a_large_correction():
    """A filter 2 m off after a long exclusion: nominal re-admission corrects most of it in
    one step; the blend spreads it over its 2 s."""
    from quadformer.config import SimConfig
    from quadformer.estimator.eskf import gps_update, init_state, noise_model

    cfg = SimConfig()
    nm = noise_model(cfg.imu, cfg.gps, cfg.vio, cfg.ekf, 100.0)
    P0 = torch.diag(torch.tensor([4.0] * 3 + [0.01] * 3 + [1e-4] * 3 + [1e-4] * 6, dtype=torch.float64))
    s0 = init_state(torch.tensor([[2.0, 0.0, 0.0]], dtype=torch.float64), torch.zeros(1, 3, dtype=torch.float64),
                    torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=torch.float64), torch.zeros(1, 3), torch.zeros(1, 3),
                    P0[None])
    att = np.zeros(40, bool)
    att[:1] = True
    scales = _drive("oracle", np.zeros(40, bool), attacked=att)["scale"][1:]   # the blend schedule
    zero = torch.zeros(1, 3, dtype=torch.float64)

    def corrections(schedule):
        s, out = s0, []
        for sc in schedule:
            before = s.p.clone()
            s, _ = gps_update(s, zero, zero, nm, std_scale=torch.tensor([sc]))
            out.append(float((s.p - before).norm()))
        return np.array(out), float(s.p.norm())

    blended, left_b = corrections(scales)
    abrupt, left_a = corrections(np.ones_like(scales))
    assert abrupt.max() > 1.5 and blended.max() < 0.4, (abrupt.max(), blended.max())
    assert left_b < 0.1 and left_a < 0.1       # both end on GPS


@pytest.fixture(scope="module")
def jump(flown):
    return {k: flown[k] for k in ("main", "no_rollback", "no_blend")}


def test_px4_gate_resets_onto_the_spoofed_fix_after_seven_seconds_in_the_loop(jump):
    r = jump["main"]
    adm, b = r["admission"], 1
    t = r["t"]
    # 69 rejected fixes, reset on the 70th: once onto the spoof, once back when the honest fixes
    # have been rejected for as long after the attack
    resets = np.nonzero(adm["reset"][b])[0]
    assert t[resets] == pytest.approx([6.0 + 6.9, 16.0 + 6.9])
    k = resets[0]
    assert not adm["fused"][b, 59:k].any() and adm["fused"][b, :59].all() and adm["fused"][b, k:159].all()
    np.testing.assert_array_equal(r["est_pos"][b, k], r["gps_pos"][b, k])           # the estimate jumps onto the spoof
    assert np.linalg.norm(adm["correction"][b, k]) > 10.0
    # the estimate now lives in the spoofed frame: the vehicle follows it (at the bounded pace of
    # its position controller) and keeps doing so after the attack, while the honest fixes are
    # rejected, until the second reset: dragged more than 10 m off its mission
    dev = np.linalg.norm(r["true_pos"][b] - r["ref_pos"][b], axis=1)
    assert dev[k:resets[1]].max() > 10.0 and dev[:59].max() < 2.0
    resilient = np.linalg.norm(r["true_pos"][0] - r["ref_pos"][0], axis=1)
    assert resilient.max() < 2.0


def test_exclusion_rolls_back_the_last_second_of_gps_corrections_in_the_loop(jump):
    r, alt = jump["main"], jump["no_rollback"]
    c = r["admission"]["correction"][0]
    e0 = int(np.argmax(~r["admission"]["fused"][0]))          # the first excluded fix
    assert e0 == 59                                            # BHT alarms on the first spoofed fix
    np.testing.assert_allclose(c[e0], -c[e0 - 10:e0].sum(0), atol=1e-12)
    assert np.linalg.norm(c[e0]) > 1e-3
    # the two runs are identical before; at the exclusion the estimate differs by the rollback
    np.testing.assert_array_equal(r["est_pos"][0, :e0], alt["est_pos"][0, :e0])
    np.testing.assert_allclose(r["est_pos"][0, e0] - alt["est_pos"][0, e0], c[e0], atol=1e-12)
    assert np.all(alt["admission"]["correction"][0, e0] == 0.0)


def test_readmission_blends_the_gps_correction_in_the_loop(jump):
    r, alt = jump["main"], jump["no_blend"]
    fused, scale = r["admission"]["fused"][0], r["admission"]["std_scale"][0]
    back = 159 + int(np.argmax(fused[159:]))                  # first fix fused after the attack
    assert not fused[back - 1] and np.array_equal(fused, alt["admission"]["fused"][0])
    # the noise is inflated 10x at re-admission and decays geometrically to nominal over 2 s
    np.testing.assert_allclose(scale[back:back + 20], 10.0 ** (1 - np.arange(20) / 20))
    assert np.all(scale[back + 20:] == 1.0) and np.all(alt["admission"]["std_scale"][0] == 1.0)
    # same state before the re-admission; the blended first correction is a fraction of the nominal one
    np.testing.assert_array_equal(r["est_pos"][0, :back], alt["est_pos"][0, :back])
    cb, cn = (np.linalg.norm(x["admission"]["correction"][0, back]) for x in (r, alt))
    assert 0 < cb < 0.5 * cn
    # over the blend both converge on GPS: the summed corrections of the two runs agree
    total_b = np.linalg.norm(r["admission"]["correction"][0, back:back + 40].sum(0))
    total_n = np.linalg.norm(alt["admission"]["correction"][0, back:back + 40].sum(0))
    assert total_b == pytest.approx(total_n, rel=0.5, abs=0.1)


def test_stale_cusum_alarm_readmits_after_a_bias_but_never_during_a_drift(flown):
    from quadformer.resilience.admission import EXCLUDE_ALARM, READMIT_STALE

    r = flown["stale"]
    a, t, att = r["admission"], r["t"], r["attacks"]
    assert list(att.kind) == ["bias", "ramp"], att.kind
    assert att.end[0] < 8.5 and att.end[1] >= _STALE.duration, att.end       # the drift lasts to the end
    stale = AdmissionConfig().stale_hold_s
    for b in (0, 1):
        first = np.nonzero(r["label"][b])[0][0]
        excl = np.nonzero(a["exclude"][b])[0]
        # excluded once, on the alarm, within 1.5 s of the onset; the alarm stands from then to the end
        assert len(excl) == 1 and a["exclude"][b, excl[0]] == EXCLUDE_ALARM and t[excl[0]] - t[first] <= 1.5
        assert a["alarm"][b, excl[0] + 20:].all()
    # the bias: once it ends, the fixes agree with the VIO-propagated estimate again and GPS is
    # re-admitted by the stale rule, stale_hold_s after the first honest fix, and stays admitted
    # under the standing alarm
    end = np.nonzero(r["label"][0])[0][-1] + 1
    back = np.nonzero(a["readmit"][0])[0]
    assert len(back) == 1 and a["readmit"][0, back[0]] == READMIT_STALE
    assert stale - 0.15 <= t[back[0]] - t[end] <= stale + 2.0, (t[end], t[back[0]])
    assert a["fused"][0, back[0]:].all() and not a["fused"][0, excl[0]:back[0]].any()
    err = np.linalg.norm(r["est_pos"][0] - r["true_pos"][0], axis=1)
    assert err.max() < 1.5, err.max()
    # the drift: the fixes keep moving away from the estimate; GPS is never re-admitted
    excl = np.nonzero(a["exclude"][1])[0][0]
    assert not a["readmit"][1].any() and not a["fused"][1, excl:].any()
    assert np.linalg.norm(r["gps_pos"][1, -1] - r["true_pos"][1, -1]) > 2.5

def test_resilience_cli_names_bad_input(tmp_path):
    runner = CliRunner()
    res = runner.invoke(app, ["resilience", "--detector", "nope", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "unknown detector 'nope'" in res.output
    res = runner.invoke(app, ["resilience", "--hold", "-1", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "hold_s" in res.output
    res = runner.invoke(app, ["resilience", "--stale-hold", "nan", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "stale_hold_s" in res.output
    res = runner.invoke(app, ["resilience", "--profile", "huge", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "unknown profile 'huge'" in res.output


def test_exclusion_precision_recall_hand_case():
    """GPS excluded against GPS spoofed, point-wise over every step of every flight.
    Flight A: spoofed steps 3-6, excluded 4-8 -> TP 3 (4, 5, 6), FP 2 (7, 8), FN 1 (3).
    Flight B (clean): excluded at step 2 -> FP 1. Pooled: P = 3/6, R = 3/4, F1 = 0.6."""
    from quadformer.evaluation.resilience import exclusion_counts, exclusion_prf, summarize_policy

    lab_a = np.zeros(10, bool)
    lab_a[3:7] = True
    fused_a = np.ones(10, bool)
    fused_a[4:9] = False
    fused_b = np.ones(10, bool)
    fused_b[2] = False
    a, b = exclusion_counts(lab_a, fused_a), exclusion_counts(np.zeros(10, bool), fused_b)
    assert a == {"excluded_tp": 3, "excluded_fp": 2, "excluded_fn": 1}
    assert b == {"excluded_tp": 0, "excluded_fp": 1, "excluded_fn": 0}
    got = exclusion_prf([a, b])
    assert got["exclusion_precision"] == pytest.approx(0.5) and got["exclusion_recall"] == pytest.approx(0.75)
    assert got["exclusion_f1"] == pytest.approx(0.6)
    # nothing excluded (naive): precision and F1 0, recall 0
    assert exclusion_prf([exclusion_counts(lab_a, np.ones(10, bool))]) == {
        "exclusion_precision": 0.0, "exclusion_recall": 0.0, "exclusion_f1": 0.0}
    # through flight_metrics and summarize_policy
    t = np.arange(10) / 10.0
    z = np.zeros((10, 3))
    rows = [flight_metrics(t, lab_a, z, z, z, fused_a), flight_metrics(t, np.zeros(10, bool), z, z, z, fused_b)]
    s = summarize_policy(rows)
    assert (s["exclusion_precision"], s["exclusion_recall"], s["exclusion_f1"]) == pytest.approx((0.5, 0.75, 0.6))


def test_oracle_exclusion_scores_one_in_the_loop(loop):
    """In closed loop the oracle excludes exactly the spoofed fixes: exclusion P = R = F1 = 1;
    the naive policy excludes nothing."""
    from quadformer.evaluation.resilience import summarize_policy

    r = loop["r"]

    def policy(p):
        return summarize_policy([flight_metrics(r["t"], r["label"][b], r["true_pos"][b], r["est_pos"][b],
                                                r["ref_pos"][b], r["admission"]["fused"][b]) for b in _rows(loop, p)])

    oracle, naive = policy("oracle"), policy("naive")
    assert oracle["exclusion_precision"] == oracle["exclusion_recall"] == oracle["exclusion_f1"] == 1.0
    assert naive["exclusion_recall"] == 0.0 and naive["exclusion_f1"] == 0.0
    assert 0.0 < policy("resilient")["exclusion_recall"] <= 1.0


def test_readmissions_are_counted_by_rule():
    """Per flight the steps where a rule re-admitted GPS; per policy the stale ones summed."""
    from quadformer.evaluation.resilience import summarize_policy
    from quadformer.resilience import READMIT_CLEAR, READMIT_STALE

    t = np.arange(12) / 10.0
    z = np.zeros((12, 3))
    lab = np.zeros(12, bool)
    lab[2:5] = True
    fused = np.ones(12, bool)
    fused[3:6] = False
    fused[8:10] = False
    readmit = np.zeros(12, np.int8)
    readmit[6], readmit[10] = READMIT_STALE, READMIT_CLEAR
    rules = lambda codes: {"clear": codes == READMIT_CLEAR, "stale": codes == READMIT_STALE}   # noqa: E731
    a = flight_metrics(t, lab, z, z, z, fused, rules(readmit))
    b = flight_metrics(t, np.zeros(12, bool), z, z, z, np.ones(12, bool), rules(np.r_[np.zeros(11), READMIT_STALE]))
    assert (a["readmissions_clear"], a["readmissions_stale"]) == (1, 1)
    assert (b["readmissions_clear"], b["readmissions_stale"]) == (0, 1)
    assert summarize_policy([a, b])["stale_readmissions"] == 2
    # without the records (a flight not flown under admission control): nothing counted
    assert "readmissions_stale" not in flight_metrics(t, lab, z, z, z, fused)
    assert summarize_policy([flight_metrics(t, lab, z, z, z, fused)])["stale_readmissions"] == 0
