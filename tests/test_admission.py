"""GPS admission's rules on hand-made per-step streams: the resilient policy's hysteresis,
rollback, stale alarms and strikes, the px4 gate, the oracle, groups and bad settings."""

from __future__ import annotations

import numpy as np
import pytest

from quadformer.resilience import Admission, AdmissionConfig, AdmissionGroup


def _drive(policy, alarm, nis=None, w=None, attacked=None, cfg=None, corrections=None):
    """Run one flight's admission over hand-made per-step inputs; returns fused, scale, reset, rollback."""
    n = len(alarm)
    nis = np.full(n, 3.0) if nis is None else nis
    w = np.zeros((n, 6)) if w is None else w
    attacked = np.zeros(n, bool) if attacked is None else attacked
    adm = Admission([policy], 10.0, cfg)
    out = {"fused": [], "scale": [], "reset": [], "rollback": []}
    for k in range(n):
        d = adm.decide(np.array([nis[k]]), w[k][None], np.array([bool(alarm[k])]), np.array([bool(attacked[k])]))
        out["fused"].append(bool(d.fuse[0]))
        out["scale"].append(float(d.std_scale[0]))
        out["reset"].append(bool(d.reset[0]))
        out["rollback"].append(d.rollback[0].copy())
        dpos = corrections[k] if corrections is not None and d.fuse[0] else np.zeros(3)
        adm.record(np.asarray(dpos)[None])
    return {k: np.array(v) for k, v in out.items()}


def test_resilient_excludes_on_alarm_and_readmits_after_hold_with_a_blend():
    alarm = np.zeros(100, bool)
    alarm[10:30] = True
    nis = np.full(100, 3.0)
    nis[30:40] = 50.0          # detector clear from 30, GPS disagrees with the estimate until 40
    r = _drive("resilient", alarm, nis)
    # clear and agreeing from step 40: 20 steps (2 s) later, at step 59, GPS is fused again
    assert r["fused"][:10].all() and not r["fused"][10:59].any() and r["fused"][59:].all()
    assert r["scale"][59] == pytest.approx(10.0)
    assert np.all(np.diff(r["scale"][59:79]) < 0)          # inflation decays ...
    assert np.all(r["scale"][79:] == 1.0)                   # ... to nominal after 2 s
    assert r["scale"][78] < 1.2


def test_hysteresis_restarts_the_hold_on_a_renewed_alarm_and_realarms_during_blend():
    alarm = np.zeros(120, bool)
    alarm[10:30] = True
    alarm[40] = True           # one more alarm during the hold: the hold starts again
    alarm[75] = True           # an alarm while blending: excluded again at once
    r = _drive("resilient", alarm, cfg=AdmissionConfig(backoff=1.0))
    assert not r["fused"][10:60].any() and r["fused"][60]   # clear from 41: 20 steps -> 60
    assert r["fused"][60:75].all() and not r["fused"][75]
    assert not r["fused"][75:95].any() and r["fused"][95]
    # with the default backoff, that exclusion 1.5 s after the re-admission is a strike: the hold
    # doubles (4 s: clear from 76, 40 steps -> 115)
    r = _drive("resilient", alarm)
    assert not r["fused"][10:60].any() and r["fused"][60:75].all()
    assert not r["fused"][75:115].any() and r["fused"][115:].all()


def _pushes(cfg=None, n=1200):
    """An attacker quieting the detector and pushing again 0.5 s after each re-admission (a 1 s
    alarm each time), five times, then leaving GPS alone for 40 s and pushing once more: the
    seconds each exclusion was held clear before its re-admission."""
    from quadformer.resilience.admission import EXCLUDE_ALARM

    adm = Admission(["resilient"], 10.0, cfg)
    holds, start, pending = [], None, 10
    for k in range(n):
        d = adm.decide(np.array([3.0]), np.zeros((1, 6)), np.array([pending <= k < pending + 10]), np.array([False]))
        adm.record(np.zeros((1, 3)))
        if d.exclude[0] == EXCLUDE_ALARM:
            start = k
        if d.readmit[0]:
            holds.append(round((k - start - 9) / 10.0, 1))
            pending = k + 5 if len(holds) < 5 else k + 400
    return holds


def test_an_attacker_who_pauses_and_pushes_again_is_held_out_longer_each_time():
    """Each exclusion within probation_s (30 s) of a re-admission is a strike that doubles the hold,
    up to max_hold_s; a re-admission that lasts probation_s clears the strikes; backoff 1: as before."""
    assert _pushes()[:6] == [2.0, 4.0, 8.0, 16.0, 32.0, 2.0]
    assert _pushes(AdmissionConfig(max_hold_s=5.0))[:6] == [2.0, 4.0, 5.0, 5.0, 5.0, 2.0]
    assert _pushes(AdmissionConfig(backoff=1.0))[:6] == [2.0] * 6
    with pytest.raises(ValueError, match="backoff"):
        AdmissionConfig(backoff=0.5)


def test_exclusion_rolls_back_the_recent_gps_corrections():
    alarm = np.zeros(30, bool)
    alarm[20:] = True
    corr = np.zeros((30, 3))
    corr[5:20] = [0.1, -0.2, 0.0]
    r = _drive("resilient", alarm, corrections=corr)
    # rollback_s = 1 s: the last 10 fused corrections (steps 10..19) are undone at step 20
    assert np.allclose(r["rollback"][20], [-1.0, 2.0, 0.0])
    assert np.allclose(np.delete(r["rollback"], 20, axis=0), 0.0)


def test_px4_gate_rejects_beyond_five_sigma_and_resets_after_seven_seconds():
    w = np.zeros((120, 6))
    w[5, 1] = 4.9                 # inside the gate
    w[10:, 0] = 6.0               # a jump the gate rejects, for good
    r = _drive("px4", np.zeros(120, bool), w=w)
    assert r["fused"][:10].all()
    assert not r["fused"][10:79].any()
    assert r["reset"][79] and r["fused"][79]                 # 70 rejections = 7 s -> reset to GPS
    assert r["reset"].sum() == 1


def test_oracle_excludes_exactly_the_spoofed_fixes():
    att = np.zeros(60, bool)
    att[10:30] = True
    r = _drive("oracle", np.ones(60, bool), attacked=att)   # the detector is ignored
    assert np.array_equal(r["fused"], ~att)
    assert r["scale"][30] == pytest.approx(10.0) and r["scale"][50] == 1.0


def test_naive_always_fuses_and_bad_settings_are_named():
    r = _drive("naive", np.ones(20, bool), nis=np.full(20, 1e6), w=np.full((20, 6), 100.0))
    assert r["fused"].all() and not r["reset"].any()
    with pytest.raises(ValueError, match="unknown admission policy 'ekf2'"):
        Admission(["naive", "ekf2"], 10.0)
    with pytest.raises(ValueError, match="blend_inflation"):
        AdmissionConfig(blend_inflation=0.5)
    with pytest.raises(ValueError, match="hold_s"):
        AdmissionConfig(hold_s=float("nan"))


def _drive_rules(alarm, nis, cfg=None):
    """Like ``_drive`` for the resilient policy, also returning the rule codes of each step."""
    adm = Admission(["resilient"], 10.0, cfg)
    fused, readmit, exclude = [], [], []
    for k in range(len(alarm)):
        d = adm.decide(np.array([nis[k]]), np.zeros((1, 6)), np.array([bool(alarm[k])]), np.array([False]))
        fused.append(bool(d.fuse[0]))
        readmit.append(int(d.readmit[0]))
        exclude.append(int(d.exclude[0]))
        adm.record(np.zeros((1, 3)))
    return np.array(fused), np.array(readmit), np.array(exclude)


def test_the_default_agreement_gate_is_the_chi_square_quantile():
    from scipy.stats import chi2

    from quadformer.resilience.admission import CHI2_6_999

    assert AdmissionConfig().readmit_nis == CHI2_6_999 == float(chi2.ppf(0.999, 6))


def test_an_admission_group_decides_each_slice_as_its_admission_alone():
    """Flights under different admission configurations in one batch: each slice's decisions
    equal those of its own admission driven alone, step for step."""
    rng = np.random.default_rng(4)
    n, cfgs = 150, [None, AdmissionConfig(rollback_s=0.0, hold_s=0.5), AdmissionConfig(blend_s=0.0, stale_hold_s=2.0)]
    policies = [["resilient", "px4"], ["resilient"], ["resilient", "oracle", "naive"]]
    B = sum(len(p) for p in policies)
    alarm = rng.random((n, B)) < np.linspace(0.05, 0.9, n)[:, None]     # more alarms as time goes on
    nis = rng.exponential(8.0, (n, B))
    w = rng.normal(0.0, 3.0, (n, B, 6))
    attacked = rng.random((n, B)) < 0.3
    dpos = rng.normal(0.0, 0.1, (n, B, 3))
    group = AdmissionGroup([Admission(p, 10.0, c) for p, c in zip(policies, cfgs)])
    alone = [Admission(p, 10.0, c) for p, c in zip(policies, cfgs)]
    bounds = np.cumsum([0] + [len(p) for p in policies])
    fields = ("fuse", "std_scale", "reset", "rollback", "readmit", "exclude")
    for k in range(n):
        args = [a[k] for a in (nis, w, alarm, attacked)]
        joined = group.decide(*args)
        group.record(dpos[k] * joined.fuse[:, None])
        for adm, a, b in zip(alone, bounds[:-1], bounds[1:]):
            d = adm.decide(*(x[a:b] for x in args))
            adm.record(dpos[k, a:b] * d.fuse[:, None])
            for f in fields:
                assert np.array_equal(getattr(joined, f)[a:b], getattr(d, f)), (k, f)
    with pytest.raises(ValueError, match="at least one admission"):
        AdmissionGroup([])


def test_stale_alarm_readmits_after_stale_hold_and_only_a_new_alarm_excludes_again():
    from quadformer.resilience.admission import EXCLUDE_ALARM, EXCLUDE_NIS, READMIT_CLEAR, READMIT_STALE

    n = 200
    alarm = np.ones(n, bool)               # the detector alarms from the start: its memory never fades
    nis = np.full(n, 3.0)
    nis[:30] = 80.0                        # the fixes disagree with the estimate until step 30
    old = AdmissionConfig(backoff=1.0)    # the rules without the strikes (tested apart)
    fused, readmit, exclude = _drive_rules(alarm, nis, old)
    # agreeing from step 30: the 50th agreeing fix (stale_hold_s = 5 s at 10 Hz), step 79, re-admits
    k = 30 + 50 - 1
    assert not fused[:k].any() and fused[k:].all()
    assert np.nonzero(readmit)[0].tolist() == [k] and readmit[k] == READMIT_STALE
    assert np.nonzero(exclude)[0].tolist() == [0] and exclude[0] == EXCLUDE_ALARM
    # the same with the stale path off: never re-admitted
    fused_off, _, _ = _drive_rules(alarm, nis, AdmissionConfig(stale_hold_s=float("inf")))
    assert not fused_off.any()

    # after the stale re-admission the alarm goes clear at 120 and rises again at 125: excluded
    # again at once, and the normal rule re-admits after the alarm clears for good (clear from
    # 150: 20 steps, hold_s = 2 s -> step 169)
    alarm2 = alarm.copy()
    alarm2[120:125] = False
    alarm2[150:] = False
    fused, readmit, exclude = _drive_rules(alarm2, nis, old)
    assert fused[k:125].all() and not fused[125:169].any() and fused[169:].all()
    assert exclude[125] == EXCLUDE_ALARM and readmit[169] == READMIT_CLEAR
    assert np.count_nonzero(exclude) == 2 and np.count_nonzero(readmit) == 2
    # the alarm that rose at 125 stood for 25 steps only: less than stale_hold_s, no stale path

    # a fix outside the gate while the stale alarm stands: excluded again; 5 s more of agreement
    nis3 = nis.copy()
    nis3[100] = 80.0
    fused, readmit, exclude = _drive_rules(alarm, nis3, old)
    assert fused[k:100].all() and not fused[100:150].any() and fused[150:].all()
    assert exclude[100] == EXCLUDE_NIS and readmit[150] == READMIT_STALE

    # the fixes never agree: never re-admitted, whatever the alarm's age
    fused, readmit, _ = _drive_rules(alarm, np.full(n, 80.0))
    assert not fused.any() and not readmit.any()
    # agreement broken every 4 s: never 5 s without a break
    nis4 = np.full(n, 3.0)
    nis4[::40] = 80.0
    fused, _, _ = _drive_rules(alarm, nis4)
    assert not fused.any()


def test_a_new_alarm_onset_restarts_the_stale_hold():
    alarm = np.ones(150, bool)
    alarm[40] = False                      # clear for one step, then a new alarm at 41
    fused, readmit, _ = _drive_rules(alarm, np.full(150, 3.0))
    # agreeing from step 1 (after the exclusion at 0); the onset at 41 restarts the count:
    # 50 agreeing fixes from step 42 -> step 91
    assert not fused[:91].any() and fused[91:].all()
    # stale_hold_s = 0: re-admitted at the first agreeing fix after the exclusion step
    fused, _, _ = _drive_rules(np.ones(20, bool), np.full(20, 3.0), AdmissionConfig(stale_hold_s=0.0))
    assert not fused[0] and fused[1:].all()


def test_stale_path_leaves_the_normal_path_and_the_other_policies_alone():
    # a short alarm: the normal rule re-admits after hold_s whatever stale_hold_s
    alarm = np.zeros(100, bool)
    alarm[10:30] = True
    for cfg in (AdmissionConfig(), AdmissionConfig(stale_hold_s=float("inf")), AdmissionConfig(stale_hold_s=3.0)):
        fused, readmit, _ = _drive_rules(alarm, np.full(100, 3.0), cfg)
        assert not fused[10:49].any() and fused[49:].all(), cfg
        assert readmit.tolist().count(1) == 1 and readmit[49] == 1, cfg       # READMIT_CLEAR
    # a stale hold shorter than the alarm: the stale path re-admits first (the 5th agreeing fix
    # after the exclusion at 10), and the alarm standing until 30 does not exclude again
    fused, readmit, _ = _drive_rules(alarm, np.full(100, 3.0), AdmissionConfig(stale_hold_s=0.5))
    assert not fused[10:15].any() and fused[15:].all() and readmit[15] == 2 and np.count_nonzero(readmit) == 1
    # oracle: the detector's standing alarm means nothing; px4, naive: unchanged
    att = np.zeros(120, bool)
    att[10:30] = True
    r = _drive("oracle", np.ones(120, bool), attacked=att, cfg=AdmissionConfig(stale_hold_s=0.0))
    assert np.array_equal(r["fused"], ~att)
    assert _drive("naive", np.ones(120, bool), cfg=AdmissionConfig(stale_hold_s=0.0))["fused"].all()


def test_bad_stale_hold_is_named():
    for bad in (float("nan"), -1.0):
        with pytest.raises(ValueError, match="stale_hold_s"):
            AdmissionConfig(stale_hold_s=bad)
    assert AdmissionConfig(stale_hold_s=float("inf")).stale_hold_s == float("inf")
