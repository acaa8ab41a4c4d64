"""A stealthy attacker who knows the detector, in the closed loop: short flights of the shipped
detectors' own simulated vehicles."""

from __future__ import annotations

import functools

import numpy as np
import pytest
from typer.testing import CliRunner

from quadformer.cli import app
from quadformer.config import AttackConfig, ConfigError, SimConfig
from quadformer.detectors import pretrained
from quadformer.simulation import simulate

ONSET = 6.0


@functools.lru_cache(maxsize=None)
def stealthy(name: str, duration: float = 18.0, flights: int = 2, seed: int = 5, **attack) -> tuple:
    """The shipped detector ``name`` and flights of the simulation it was calibrated on, every one
    attacked from ONSET by a stealthy attacker who evades it (flown once per module for the same
    arguments: the tests read them, none changes them)."""
    det = pretrained.load(name)
    sim = dict(det.calibration_["sim_config"])
    sim.update(flights=flights, duration=duration, batch_size=flights, seed=seed)
    sim["attack"] = {"kind": "stealthy", "detector": name, "fraction": 1.0, "onset": (ONSET, ONSET), **attack}
    return det, simulate(SimConfig.from_dict(sim)).flights


def offset(flights, t: float) -> np.ndarray:
    """Each flight's spoofed horizontal offset (m) at time t."""
    at = flights[np.isclose(flights.t, t)]
    return np.hypot(at.atk_d_x, at.atk_d_y).to_numpy()


def test_white_box_attacker_keeps_a_cusum_under_its_threshold_and_still_moves_the_fix():
    # margin 0.7: the attacker knows the fix it sends, not the next fix's noise; on this vehicle's
    # exponential GPS noise a score kept at 0.9 x threshold was pushed over it by a later fix (seed 5:
    # 213 and 223 against 196), at 0.7 it stays under with the same offset within 5 %
    det, flights = stealthy("vio-cusum", margin=0.7)
    scores = det.decision_function(flights)            # the defender's own detector, offline
    assert scores.max() <= det.threshold_
    assert (flights.label[flights.t >= ONSET] == 1).all() and (flights.label[flights.t < ONSET] == 0).all()
    moved = offset(flights, 18.0)
    assert (moved > 1.5).all()                          # 12 s of attack: 3.2 and 3.6 m measured
    assert (moved < 12 * 3.0).all()                     # never faster than its top speed, 3 m/s


def test_against_a_detector_without_memory_the_offset_grows_on_under_the_bound():
    det, flights = stealthy("vio-chi2", margin=0.9)
    scores = det.decision_function(flights)
    # the score of each fix is what the attacker computed for it: at or under 0.9 x threshold
    # wherever one of its candidate speeds was (a fix whose own noise is above would be over it: none
    # on this seed, 2 % allowed)
    over = scores[flights.t.to_numpy() >= ONSET] > 0.9 * det.threshold_ + 1e-9
    assert over.mean() <= 0.02
    assert scores.max() <= det.threshold_
    early, late = offset(flights, ONSET + 6.0), offset(flights, ONSET + 12.0)
    assert (late > 1.4 * early).all()                   # still growing after 12 s: 7.0-7.3 m, then 12.2-12.6 m
    _, with_memory = stealthy("vio-cusum", margin=0.9)
    assert (late > 2.0 * offset(with_memory, ONSET + 12.0)).all()  # a CUSUM's memory holds it to 3-4 m


def test_black_box_attacker_accelerates_in_at_its_budget_up_to_its_top_speed():
    _, flights = stealthy("vio-cusum", duration=14.0, flights=1, knowledge="black", accel=(0.5, 0.5),
                          rate=(2.0, 2.0))
    dt = 0.1                                            # the GPS period
    k = np.arange(1, 81)                                # the fixes from the onset to the end
    expect = np.cumsum(np.minimum(k * 0.5 * dt, 2.0) * dt)
    got = np.hypot(flights.atk_d_x, flights.atk_d_y).to_numpy()[flights.t.to_numpy() >= ONSET - 1e-9]
    np.testing.assert_allclose(got[:len(expect)], expect, atol=1e-9)


@pytest.mark.parametrize("attack, message", [
    ({"kind": "stealthy"}, "attack.detector: a stealthy attack needs the detector it evades"),
    ({"kind": "stealthy", "detector": "vio-cusum", "margin": 0.0}, "attack.margin: must be in (0, 1]"),
    ({"kind": "stealthy", "detector": "vio-cusum", "margin": 1.5}, "attack.margin: must be in (0, 1]"),
    ({"kind": "stealthy", "detector": "vio-cusum", "knowledge": "purple"},
     "attack.knowledge: unknown knowledge 'purple'; choose from white, grey, black"),
    ({"kind": "stealthy", "detector": "vio-cusum", "knowledge": "grey"},
     "attack.surrogate: a grey-box attacker runs its own copy of the method"),
    ({"kind": "stealthy", "detector": "vio-cusum", "surrogate": "vio-cusum"},
     "attack.surrogate: only a grey-box attacker runs a surrogate (attack.knowledge 'white')"),
    ({"kind": "ramp", "margin": 0.5}, "attack.margin: only a stealthy attack takes it"),
])
def test_impossible_stealthy_attacks_are_refused_naming_the_field(attack, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        AttackConfig(**attack)


@pytest.mark.parametrize("args, message", [
    (["--attack-detector", "vio-nothing"], "attack.detector: 'vio-nothing' is neither a model file nor a shipped"),
    (["--attack-detector", "vio-quadformer", "--sensors", "gps+imu+mag+baro"],
     "attack.detector: vio-quadformer reads res_vio"),
])
def test_simulate_refuses_a_detector_it_cannot_evade_before_flying(tmp_path, args, message):
    out = tmp_path / "ds"
    res = CliRunner().invoke(app, ["simulate", "--out", str(out), "--attack", "stealthy", "--flights", "1",
                                   "--duration", "8", "--onset", "2,2", "--quiet", *args])
    assert res.exit_code != 0
    assert message in res.output
    assert not out.exists()


def test_grey_box_attacker_keeps_its_surrogate_under_its_bound_and_is_judged_by_the_vehicles(tmp_path):
    # the surrogate: the shipped CUSUM with a larger drift allowance (8 against the vehicle's 4: each
    # step's NIS may reach 6 + 8 sqrt(12) before its sum grows); kept under that, the vehicle's own
    # CUSUM, which sums what passes 6 + 4 sqrt(12), alarms: the attacker did not know its calibration
    det = pretrained.load("vio-cusum")
    sur = pretrained.load("vio-cusum").set_params(drift=8.0)
    path = sur.save(tmp_path / "surrogate.json")
    _, grey = stealthy("vio-cusum", margin=0.7, knowledge="grey", surrogate=str(path))
    _, white = stealthy("vio-cusum", margin=0.7)
    assert sur.decision_function(grey).max() <= sur.threshold_          # under its own threshold
    s = det.decision_function(grey)
    attacked = grey.t.to_numpy() >= ONSET
    assert (s[~attacked] <= det.threshold_).all() and s.max() > det.threshold_     # the vehicle's alarms
    assert det.decision_function(white).max() <= det.threshold_         # as the white box's never does
    assert (offset(grey, 18.0) > offset(white, 18.0)).all()             # it pushed harder


def test_grey_box_surrogate_is_fitted_on_the_attackers_own_flights(tmp_path):
    from quadformer.detectors.registry import load
    from quadformer.experiments.stealth import StealthPlan, fit_surrogate, run_stealth, surrogate_config

    det = pretrained.load("vio-cusum")
    plan = StealthPlan(detectors=("vio-cusum", "vio-quadformer"), knowledge=("grey",), flights=1,
                       horizons=(2.0, 4.0), onset=4.0, margins=(0.5,), rehearse=(0.5,))
    cfg = surrogate_config(det, plan)
    vehicle = det.calibration_["sim_config"]
    assert cfg.model != vehicle["model"] and cfg.seed != plan.seed and cfg.attack.kind == "none"
    info = fit_surrogate(det, plan, tmp_path / "sur.json")
    sur = load(tmp_path / "sur.json")
    assert sur.name == "cusum" and sur.threshold_ == pytest.approx(info["threshold"])
    assert sur.threshold_ != pytest.approx(det.threshold_)             # its own calibration, not the vehicle's
    with pytest.raises(ValueError, match="is a network"):
        fit_surrogate(pretrained.load("vio-quadformer"), plan, tmp_path / "q.json")
    res = run_stealth(plan, tmp_path / "run", echo=lambda s: None)
    assert [(r["detector"], r["knowledge"]) for r in res["runs"]] == [("vio-cusum", "grey")]
    assert res["runs"][0]["surrogate"]["model"] == cfg.model
    tried = res["runs"][0]["rehearsal"]["tried"]          # rehearsed against its surrogate, on its own flights
    assert [x["accel"] for x in tried] == [None, 0.5] and all(x["deviation_median"] > 0 for x in tried)
    assert res["not_run"] == [{"detector": "vio-quadformer", "knowledge": "grey",
                               "reason": "a network: the attacker would train its own"}]


def test_simulate_refuses_a_surrogate_of_another_method(tmp_path):
    out = tmp_path / "ds"
    res = CliRunner().invoke(app, ["simulate", "--out", str(out), "--attack", "stealthy", "--attack-detector",
                                   "vio-cusum", "--knowledge", "grey", "--surrogate", "vio-chi2", "--flights", "1",
                                   "--duration", "8", "--onset", "2,2", "--quiet"])
    assert res.exit_code != 0
    assert "attack.surrogate: vio-chi2 is a chi2 detector and vio-cusum a cusum one" in res.output
    assert not out.exists()


def test_envelope_is_the_largest_deviation_before_the_first_alarm_per_horizon():
    import pandas as pd

    from quadformer.experiments.stealth_envelope import envelope

    t = np.arange(0.0, 21.0)                            # one flight at 1 Hz, onset at 10 s
    flights = pd.DataFrame({"flight_id": 0, "t": t, "est_pos_x": 0.3 * np.maximum(t - 10.0, 0.0), "true_pos_x": 0.0,
                            "est_pos_y": 0.0, "true_pos_y": 0.0, "atk_d_x": 0.0, "atk_d_y": 0.0})
    scores = np.where(t >= 15.0, 5.0, 0.0)              # the first alarm at 15 s
    scores[3] = 9.0                                     # and one before the onset
    flights["gps_fused"] = (t < 15.0).astype(int)       # the resilient policy excludes GPS from the alarm
    (row,) = envelope(flights, scores, threshold=1.0, onset=10.0, horizons=(3.0, 10.0))
    assert row["alarm_before_onset"] and row["first_alarm_s"] == 5.0
    assert row["deviation_3"] == pytest.approx(0.6) and row["hidden_3"]          # t = 10, 11, 12
    assert row["deviation_10"] == pytest.approx(1.2) and not row["hidden_10"]    # up to t = 14, then seen
    assert row["reached_10"] == pytest.approx(2.7)                               # up to t = 19, alarm or not
    assert row["deviation_at_alarm"] == pytest.approx(1.5)
    assert row["fused_after_onset"] == pytest.approx(5 / 11)                     # t = 10 to 14 of 10 to 20
    assert row["at_threshold"] == 0.0
    # a score held at a ceiling its threshold sits on never alarms: the steps held there are counted
    held = np.where(t >= 12.0, 4.5, 0.0)
    (row,) = envelope(flights, held, threshold=4.5, onset=10.0, horizons=(10.0,))
    assert row["first_alarm_s"] is None and row["at_threshold"] == pytest.approx(9 / 11)


def test_physical_bound_grows_with_time_and_is_far_wider_without_a_camera():
    from quadformer.experiments.stealth import PROFILES, stealth_config
    from quadformer.experiments.stealth_envelope import physical_bound

    plan = PROFILES["stealth"]
    vio = physical_bound(stealth_config("vio-cusum", plan, "black", None), (10.0, 60.0, 200.0))
    magbaro = physical_bound(stealth_config("magbaro-cusum", plan, "black", None), (10.0, 60.0))
    assert vio["10"] < vio["60"] < vio["200"] and magbaro["10"] < magbaro["60"]
    # with VIO the reference barely drifts: the receiver's slow error (0.5 m, 30 s) sets it, 3 sqrt(2) 0.5
    assert vio["200"] == pytest.approx(3 * np.sqrt(2) * 0.5, rel=0.1)
    assert magbaro["60"] > 10 * vio["60"]


def test_stealth_benchmark_writes_its_results_and_report(tmp_path):
    import json

    from quadformer.experiments.stealth import StealthPlan, run_stealth

    plan = StealthPlan(detectors=("vio-cusum",), flights=1, horizons=(2.0, 4.0), onset=4.0, margins=(0.5,))
    res = run_stealth(plan, tmp_path, echo=lambda s: None, profile="test")
    assert [(r["knowledge"], r["margin"]) for r in res["runs"]] == [("white", 0.5), ("black", None)]
    saved = json.loads((tmp_path / "results.json").read_text())
    assert saved["provenance"]["profile"] == "test" and set(saved["bounds"]) == {"vio"}
    for r in saved["runs"]:
        s = r["summary"]
        assert s["deviation_median_2"] <= s["deviation_median_4"] and 0.0 <= s["hidden_4"] <= 1.0
    page = (tmp_path / "report.html").read_text()
    assert "worst / bound" in page and "<img" in page            # the table, and the envelope curves


def test_under_the_resilient_policy_an_alarm_takes_gps_out_of_the_loop_and_stops_the_attack(tmp_path):
    # the memoryless gate against a white box at 0.9 of its threshold: on this seed one flight's
    # later fix noise crosses it (6.1 s into the attack); with its alarms in the loop GPS is
    # excluded from then on and the deviation stays near where the alarm found it (4.9 m, then 5.4 m
    # on VIO and IMU alone, against 7.5 m with GPS fused)
    from quadformer.experiments.stealth import StealthPlan, run_stealth

    plan = StealthPlan(detectors=("vio-chi2",), knowledge=("white",), margins=(0.9,), flights=2,
                       horizons=(5.0, 15.0), onset=5.0, policies=("none", "resilient"))
    res = run_stealth(plan, tmp_path, echo=lambda s: None)
    free, guarded = res["runs"]
    assert (free["policy"], guarded["policy"]) == ("none", "resilient")
    for f, g in zip(free["flights"], guarded["flights"]):
        assert f["first_alarm_s"] == g["first_alarm_s"]          # the same attack until the first alarm
        if g["first_alarm_s"] is None:
            assert g["fused_after_onset"] == 1.0 and g["reached_15"] == pytest.approx(f["reached_15"])
        else:                                                     # GPS left the fusion, the drift stopped
            assert g["fused_after_onset"] < 0.9
            assert g["reached_15"] < f["reached_15"] - 1.0 and g["reached_15"] < g["deviation_at_alarm"] + 1.0
    assert any(g["first_alarm_s"] is not None for g in guarded["flights"])
    # a run of the resilient policy alone has its own table and no curves of the unguarded envelope
    from quadformer.report.stealth import write_stealth_report

    page = write_stealth_report({**res, "runs": [guarded]}, tmp_path / "resilient.html").read_text()
    assert "Under the resilient GPS policy" in page and "Deviation unseen" not in page


@pytest.mark.parametrize("args, message", [
    (["--methods", "vio-nothing"], "--methods: no shipped detector 'vio-nothing'"),
    (["--methods", "vio-cusum", "--policies", "sometimes"], "--policies: stealth: policies must name some of none"),
    (["--data", "somewhere"], "--profile stealth flies each shipped detector's own simulation"),
    (["--profile", "stealth-slow"], "the stealth profiles are stealth, stealth-quick"),
    (["--methods", "vio-cusum", "--headings", "9"], "--headings: stealth: headings must be a whole number from 1 to 8"),
    (["--methods", "vio-cusum", "--rehearse", "fast"], "--rehearse: could not convert string to float"),
    (["--methods", "vio-cusum", "--rehearse", "0.1,-1"], "--rehearse: stealth: rehearse takes positive"),
    (["--methods", "vio-cusum", "--rehearse", "0.1", "--headings", "2"], "--headings: stealth: a rehearsed plan"),
])
def test_stealth_benchmark_refuses_what_it_cannot_fly(tmp_path, args, message):
    full = ["benchmark", "--out", str(tmp_path / "run"), *(["--profile", "stealth"] if "--profile" not in args else []),
            *args]
    res = CliRunner().invoke(app, full)
    assert res.exit_code != 0 and message in res.output


def test_simulate_writes_a_stealthy_dataset_from_the_command_line(tmp_path):
    import pandas as pd

    out = tmp_path / "ds"
    res = CliRunner().invoke(app, ["simulate", "--out", str(out), "--attack", "stealthy", "--attack-detector",
                                   "vio-cusum", "--margin", "0.5", "--flights", "1", "--duration", "6",
                                   "--onset", "2,2", "--attack-fraction", "1", "--quiet"])
    assert res.exit_code == 0, res.output
    scen = pd.read_parquet(out / "scenarios.parquet")
    assert scen.attack_type.tolist() == ["stealthy"] and scen.rate.tolist() == [3.0]
    flights = pd.read_parquet(out / "flights.parquet")
    assert (flights.attack_type[flights.t >= 2.0] == "stealthy").all()
    assert (np.hypot(flights.atk_d_x, flights.atk_d_y)[flights.t < 2.0] == 0).all()


def test_a_white_box_searching_across_the_track_keeps_a_cusum_under_its_threshold():
    """Four axes each GPS step (``headings``): the fix goes wherever it can go farthest unseen;
    the defender's CUSUM still never alarms, and the fix moves no faster than the top speed."""
    det, flights = stealthy("vio-cusum", margin=0.7, headings=4)
    assert det.decision_function(flights).max() <= det.threshold_
    moved = offset(flights, 18.0)
    assert (moved > 1.5).all() and (moved < 12 * 3.0 + 1e-6).all()


@pytest.mark.parametrize("attack, message", [
    ({"headings": 0}, "attack.headings"), ({"headings": 9}, "attack.headings"),
    ({"headings": 2, "knowledge": "black"}, "only a white or grey box"),
])
def test_impossible_headings_are_refused(attack, message):
    with pytest.raises(ConfigError, match=message):
        AttackConfig(kind="stealthy", detector="vio-cusum", fraction=1.0, **attack)


def test_a_white_box_with_a_plan_keeps_its_pace_and_the_cusum_under_its_threshold():
    """A plan of 0.5 m/s^2: the push's speed grows by at most 0.05 m/s a fix (10 Hz), and is held
    back where the score would pass the bound; the defender's CUSUM never alarms."""
    det, flights = stealthy("vio-cusum", margin=0.7, plan_accel=0.5)
    assert det.decision_function(flights).max() <= det.threshold_
    for _, g in flights.groupby("flight_id"):
        g = g[g.t >= ONSET - 1e-9]
        d = np.hypot(g.atk_d_x, g.atk_d_y).to_numpy()
        fixes = np.flatnonzero(np.r_[True, np.diff(d) != 0])          # the rows a new fix changed the offset
        speed = np.diff(np.r_[0.0, d[fixes]]) / 0.1
        assert np.diff(np.r_[0.0, speed]).max() <= 0.05 + 1e-9
        assert d[-1] > 1.0                                            # it still moved: 12 s of attack
    _, fastest = stealthy("vio-cusum", margin=0.7)
    assert not np.allclose(offset(flights, 18.0), offset(fastest, 18.0))   # the plan changed the attack


@pytest.mark.parametrize("attack, message", [
    ({"plan_accel": 0.0}, "attack.plan_accel: must be a positive acceleration"),
    ({"plan_accel": float("nan")}, "attack.plan_accel: must be a positive acceleration"),
    ({"plan_accel": 0.1, "knowledge": "black"}, "only a white or grey box follows a plan"),
    ({"plan_accel": 0.1, "headings": 2}, "with it, headings must be 1"),
])
def test_impossible_plans_are_refused(attack, message):
    with pytest.raises(ConfigError, match=message):
        AttackConfig(kind="stealthy", detector="vio-cusum", fraction=1.0, **attack)


def test_a_rehearsing_attacker_flies_the_plan_that_went_farthest_unseen_on_its_own_flights(tmp_path):
    from quadformer.experiments.stealth import REHEARSAL_FLIGHTS, StealthPlan, run_stealth

    plan = StealthPlan(detectors=("vio-chi2",), knowledge=("white",), margins=(0.9,), flights=1, horizons=(6.0,),
                       onset=4.0, rehearse=(0.2,))
    run, = run_stealth(plan, tmp_path, echo=lambda s: None)["runs"]
    r = run["rehearsal"]
    assert [x["accel"] for x in r["tried"]] == [None, 0.2] and r["flights"] == REHEARSAL_FLIGHTS
    assert r["seed"] != plan.seed                                    # its own flights, not those it attacks
    best = max(r["tried"], key=lambda x: x["deviation_median"])
    assert r["accel"] == best["accel"]
    # a plan of 0.2 m/s^2 moves the fix 3.7 m at the most in 6 s (1.7 m of deviation measured); the
    # fastest push, chi2 without memory, moves it 7.3 m under the bound (3.4 m of deviation): farther
    assert r["tried"][1]["deviation_median"] < 3.7 and r["accel"] is None
    assert run["flights"][0]["offset_end"] > 3.7                     # flown as the fastest push
