"""The field benchmark: the fleet manifest, and a run on logs the project writes itself."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pandas as pd
import pytest

from quadformer.logs.manifest import INSTANT_WINDOW, ManifestError, read_manifest, trouble_windows

from logs_support import FIX


def test_trouble_text_gives_windows_and_first_signs():
    text = ("in-air GPS fix<3 (t_rel s): 69.7-74.7; 95.1-107.6 ... | ERR GPS-glitch(11/2) at 69.7,120.0 "
            "| ERR EKF-check(16/2) at 151.6")
    windows, signs = trouble_windows(text)
    lo, hi = INSTANT_WINDOW
    # the fix losses as given, the glitch at 69.7 inside the first, the one at 120 its own window; the EKF
    # check names no GPS trouble and is left out
    assert windows == [(69.7 + lo, 69.7 + hi), (95.1, 107.6), (120.0 + lo, 120.0 + hi)]
    assert signs == [69.7, 95.1, 120.0]
    assert trouble_windows("") == ([], [])
    assert trouble_windows("STATUSTEXT \"GPS Glitch\" at t_rel 244.3-273.4, 278.4-318.7 s while DISARMED")[1] == \
        [244.3, 278.4]


def test_manifest_columns_and_errors(tmp_path):
    good = tmp_path / "m.csv"
    good.write_text("file,clean,gps_trouble,vehicle\na.bin,yes,,quad\nb.bin,no (GPS degraded),fix lost 10-12,quad\n")
    m = read_manifest(good)
    assert m["a.bin"].clean and not m["b.bin"].clean
    assert m["b.bin"].trouble == [(10.0, 12.0)] and m["b.bin"].signs == [10.0]
    assert m["a.bin"].extra == {"vehicle": "quad"}
    bad = tmp_path / "bad.csv"
    bad.write_text("name,clean\na.bin,yes\n")
    with pytest.raises(ManifestError, match="needs the columns file and clean"):
        read_manifest(bad)
    twice = tmp_path / "twice.csv"
    twice.write_text("file,clean\na.bin,yes\na.bin,no\n")
    with pytest.raises(ManifestError, match="row 3: a.bin is listed twice"):
        read_manifest(twice)
    with pytest.raises(ManifestError, match="cannot read"):
        read_manifest(tmp_path / "missing.csv")


# -- the benchmark end to end, on logs the project writes ---------------------------------

SPAN = 25.0    # s of each log the benchmark reads (the filter's replay is the cost)


@pytest.fixture(scope="module")
def field_run(tmp_path_factory):
    """Three 25-s ArduCopter logs cut from the simulated fixture log and written again: two clean
    (its first and its last 25 s) and a copy of the first whose receiver loses its fix for 2 s
    (fix type 1 from 12 s after its first GPS sample), with a manifest saying so; two classical
    methods trained on 4 short simulated flights."""
    from quadformer.experiments.field import FieldPlan, run_field
    from quadformer.logs import read_log
    from quadformer.logs.dataflash_writer import write_dataflash
    from quadformer.logs.writing import LogHeader

    d = tmp_path_factory.mktemp("field")
    full = read_log(FIX / "sim_copter.bin")

    def cut(a: float):
        return dataclasses.replace(full, segments=[(a, a + SPAN)], events=None).segment(0)

    first, last = cut(0.0), cut(full.duration - SPAN)
    gps = first.gps.copy()
    rel = gps["t"] - gps["t"].iloc[0]
    gps.loc[(rel >= 12.0) & (rel < 14.0), "fix_type"] = 1.0
    paths = [write_dataflash(first, d / "first.bin", LogHeader(airborne=True)),
             write_dataflash(last, d / "last.bin", LogHeader(airborne=True)),
             write_dataflash(dataclasses.replace(first, gps=gps), d / "lost.bin", LogHeader(airborne=True))]
    man = d / "manifest.csv"
    man.write_text("file,clean,gps_trouble\nfirst.bin,yes,\nlast.bin,yes,\n"
                   "lost.bin,no,in-air GPS fix<3 (t_rel s): 12.0-14.0\n")
    plan = FieldPlan(("chi2", "cusum"), flights=4, duration=12.0, injections=1)
    out = d / "run"
    return run_field(paths, out, plan, man, echo=lambda s: None), out


def test_field_benchmark_counts_false_alarms_degradation_and_injected_spoofs(field_run):
    res, out = field_run
    assert [r["clean"] for r in res["read"]] == [True, True, False] and res["refused"] == []
    # every flight is airborne from its first sample (take-off event at 0): in air after the 5 s settle,
    # counted from the replayed filter's first row (it starts once it has the IMU, a fix and a heading)
    for r in res["read"]:
        assert r["phase_source"] == "events"
        assert (SPAN - 5.0 - 4.0) / 3600 <= r["air_hours"] <= (SPAN - 5.0 + 0.2) / 3600     # +- one GPS step
    fa = {(r["method"], r["threshold"]): r for r in res["false_alarms"]}
    assert set(fa) == {(m, t) for m in ("chi2", "cusum") for t in ("sim", "calibrated")}
    clean_hours = sum(r["air_hours"] for r in res["read"] if r["clean"])
    for r in fa.values():
        assert r["logs"] == 2 and r["air_hours"] == pytest.approx(clean_hours)
        assert r["ci_low"] <= r["per_air_hour"] <= r["ci_high"]
    # the fix loss: a degraded alert at its first report without a fix, inside the manifest's window
    (sign,) = res["receiver"]
    assert sign["covered"] and sign["delay_s"] <= 0.2 and sign["sign_s"] == pytest.approx(12.0)
    for r in res["troubles"]:
        assert r["windows"] == 1 and r["in_window_degraded"] >= 1
        assert r["in_window_spoofing"] >= r["in_window_spoofing_air"] + r["in_window_spoofing_transition"]
    # one spoof of each kind injected into each clean log, scored by each method at both thresholds
    inj = pd.read_csv(out / "injections.csv")
    kinds = {"bias": (1.0, 10.0), "ramp": (0.05, 2.0), "drift": (0.2, 2.0), "drift-accel": (0.2, 2.0),
             "capture": (5.0, 15.0)}
    assert len(inj) == 5 * 2 * 2 * 2 and set(inj["kind"]) == set(kinds)
    for kind, (lo, hi) in kinds.items():
        size = inj.loc[inj.kind == kind, "size"]
        assert ((size >= lo) & (size <= hi)).all(), kind
    assert {r["kind"] for r in res["injection"]} == set(kinds)
    hit = inj[inj.detected]
    assert (hit["delay_s"] >= 0).all() and (hit["offset_at_detection_m"] >= 0).all()
    # the seconds in the air before each onset: the onsets fall in the air, at most the span less the
    # 5-s settle and the 12 s kept after them; none after 30 s, so every spoof counts as early
    assert ((inj["air_before_s"] >= 0) & (inj["air_before_s"] <= SPAN - 5.0 - 12.0 + 0.2)).all()
    for r in res["injection"]:
        assert r["settled_injected"] == 0 and np.isnan(r["recall_settled"])
        assert r["recall_early"] == pytest.approx(r["event_recall"])
    # the tuned detectors are cached with the simulation they were fit on (detect replays with its tuning)
    from quadformer.detectors import load

    assert load(out / "models" / "chi2.qfm").calibration_["sim_config"]["duration"] == 12.0
    page = (out / "report.html").read_text()
    assert "False alarms on clean flights" in page and page.count("<img") >= 3
    assert "<th>package</th><th>version</th>" in page
    # how it was produced, as written to results.json: the field profile and the plan's seed
    written = json.loads((out / "results.json").read_text())["provenance"]
    assert (written["profile"], written["seeds"]) == ("field", {"plan": 0})


def test_field_cli_refuses_what_it_cannot_run(tmp_path):
    from typer.testing import CliRunner

    from quadformer.cli import app

    run = CliRunner().invoke
    res = run(app, ["benchmark", "--profile", "field", "--out", str(tmp_path / "o")])
    assert res.exit_code != 0 and "needs --logs" in res.output
    res = run(app, ["benchmark", "--profile", "quick", "--logs", str(FIX / "sim_copter.bin")])
    assert res.exit_code != 0 and "belong to --profile field" in res.output
    res = run(app, ["benchmark", "--profile", "field", "--logs", str(FIX / "sim_copter.bin"), "--manifest",
                    str(tmp_path / "none.csv")])
    assert res.exit_code != 0 and "is not a file" in res.output


def test_an_injected_capture_is_labelled_with_its_spoofed_receiver():
    """A capture injected into a clean log: its alerts are labelled with the receiver's spoofed
    reports (satellites dropping, eph inflating, the lock lost at its start), which raise a
    degraded episode at the capture; the log's own clean reports raise none there."""
    from quadformer.detectors import make
    from quadformer.detectors.flight_phase import PhaseRule
    from quadformer.estimator.filter_config import FilterConfig
    from quadformer.experiments.field import FieldPlan, _with_threshold, replay_logs
    from quadformer.experiments.field_spoofs import inject, log_alerts
    from quadformer.logs import read_log

    path = FIX / "sim_copter.bin"
    log = read_log(path)
    log = dataclasses.replace(log, receiver=log.receiver.assign(satellites=11.0))   # the writer logged none
    (fl,), _ = replay_logs({path: log}, None, FilterConfig(), PhaseRule(), echo=lambda s: None)
    plan = FieldPlan(("chi2",), injections=2, kinds=("capture",))
    injected = inject(plan, fl, 0, FilterConfig())
    assert len(injected) == 2 and {i.kind for i in injected} == {"capture"}
    det = _with_threshold(make("chi2").fit(fl.rows), float("inf"))       # only the receiver raises alerts
    for inj in injected:
        rec, clean = inj.receiver, fl.log.receiver
        during = (rec.t >= inj.onset) & (rec.t < inj.onset + 4.0)
        assert rec.loc[during, "satellites"].min() < 0.55 * clean["satellites"].max()
        assert rec.loc[during, "eph"].max() > 2.9 * clean["eph"].max()
        assert (rec.loc[rec.t >= inj.onset + 10.0, "eph"] == clean.loc[rec.t >= inj.onset + 10.0, "eph"]).all()
        spoofed = [a for a in log_alerts(fl, inj.rows, np.zeros(len(inj.rows)), det, 10.0, receiver=rec)
                   if a.kind == "degraded" and inj.onset <= a.start_s < inj.onset + 4.0]
        honest = [a for a in log_alerts(fl, inj.rows, np.zeros(len(inj.rows)), det, 10.0)
                  if a.kind == "degraded" and inj.onset <= a.start_s < inj.onset + 4.0]
        assert spoofed and not honest
    with pytest.raises(ValueError, match="FieldPlan.kinds: unknown injection 'jam'"):
        FieldPlan(("chi2",), kinds=("bias", "jam"))
