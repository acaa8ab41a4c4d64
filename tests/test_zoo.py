"""The shipped detectors: their files load and match their checksums, score flights, are picked
by the data's sensors, and `detect` / `monitor` / the Python API run without a model of one's own;
`zoo build` gives the same files twice."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import quadformer
from quadformer.cli import app
from quadformer.detectors import pretrained

FIX = Path(__file__).resolve().parent / "fixtures" / "logs"
COPTER = FIX / "sim_copter.bin"                 # written by the project: ArduPilot DataFlash
PX4 = FIX / "sample_px4_events.ulg"             # pyulog's sample: PX4 SITL, GPS, IMU, mag, baro
runner = CliRunner()


def test_every_shipped_detector_loads_matches_its_checksum_and_has_a_card():
    entries = pretrained.entries()
    assert {e.set.name for e in entries.values()} == {"magbaro", "vio", "px4", "ardupilot"}
    assert {"vio-quadformer", "magbaro-quadformer"} <= set(entries)
    total = 0
    for name, e in entries.items():
        pretrained.verify(name)
        total += sum((pretrained.ROOT / f).stat().st_size for f in e.files)
        det = pretrained.load(name)
        assert det.threshold_ == e.card["calibration"]["budget_threshold"]
        assert pretrained.load(name, threshold="f1").threshold_ == e.card["calibration"]["f1_threshold"]
        c = e.card
        assert c["training"]["simulation"] and all(s["seed"] for s in c["training"]["simulation"])
        assert c["test"]["flights"] > 0 and 0.0 <= c["test"]["at_f1_threshold"]["f1"] <= 1.0
        assert "torch" in c["versions"] and c["rates"]["gps_hz"] > 0
    assert total < 8e6                          # a few MB in all


def test_shipped_networks_score_a_flight_the_same_as_their_validation_calibration(bias_dataset):
    """The vio set's QUADFormer and CUSUM score a simulated gps+imu+vio flight: finite scores, one
    per step, alarms on the attacked flights' steps more than on the clean ones'."""
    X = bias_dataset.flights
    for name in ("vio-quadformer", "vio-cusum"):
        det = pretrained.load(name, threshold="f1")
        s = det.decision_function(X)
        assert s.shape == (len(X),) and np.isfinite(s).all()
        alarms = s > det.threshold_
        y = X.label.to_numpy() == 1
        assert alarms[y].mean() > alarms[~y].mean(), name


def test_a_damaged_or_unknown_shipped_detector_is_named(tmp_path):
    root = tmp_path / "zoo"
    shutil.copytree(pretrained.ROOT, root)
    victim = root / "magbaro-cusum.qfm"
    doc = json.loads(victim.read_text())
    doc["state"]["threshold_"] = 0.0
    victim.write_text(json.dumps(doc))
    with pytest.raises(pretrained.ZooError, match="magbaro-cusum.qfm has SHA-256 .* the file was changed"):
        pretrained.load("magbaro-cusum", root=root)
    (root / "magbaro-chi2.qfm").unlink()
    with pytest.raises(pretrained.ZooError, match="magbaro-chi2.qfm is missing"):
        pretrained.load("magbaro-chi2", root=root)
    with pytest.raises(pretrained.ZooError, match="no shipped detector 'nope'"):
        pretrained.load("nope")
    with pytest.raises(pretrained.ZooError, match="threshold"):
        pretrained.load("magbaro-cusum", threshold="median")


@pytest.mark.parametrize("have, residues, fmt, expected", [
    ({"gps", "imu", "mag", "baro"}, "ekf", "ardupilot", "magbaro"),
    ({"gps", "imu", "vio", "mag", "baro"}, "ekf", "px4", "magbaro"),
    ({"gps", "imu", "vio"}, "ekf", "ros", "vio"),
    ({"gps", "imu", "mag", "baro"}, "autopilot", "px4", "px4"),
    ({"gps", "imu", "baro"}, "ekf", "ardupilot", "magbaro"),     # a log without a compass
])
def test_the_shipped_detector_that_fits_the_data_is_chosen(have, residues, fmt, expected):
    chosen = pretrained.choose(have, residues, fmt)
    assert chosen.set.name == expected and chosen.name == pretrained.sets()[expected].default
    assert pretrained.needs(chosen.name) <= have or residues == "autopilot"
    if residues == "ekf":      # the replay fuses the set's sensors the data has
        assert pretrained.fused_sensors(chosen, have) == "+".join(
            s for s in ("gps", "imu", "vio", "mag", "baro") if s in have and s in chosen.set.parts)
    assert pretrained.resolve("gps+imu+mag+baro").name == pretrained.sets()["magbaro"].default
    assert pretrained.resolve("vio").name == pretrained.sets()["vio"].default


@pytest.mark.parametrize("have, residues, fmt, message", [
    ({"gps", "vio"}, "ekf", "ros", "no shipped detector fits ekf residues of gps\\+vio"),
    ({"gps", "imu", "mag", "baro"}, "autopilot", "tlog", "autopilot residues .* from a tlog log"),
])
def test_data_no_shipped_detector_fits_is_named_with_what_to_do(have, residues, fmt, message):
    with pytest.raises(pretrained.ZooError, match=message) as e:
        pretrained.choose(have, residues, fmt)
    assert "--model" in str(e.value)


def test_detect_log_without_a_detector_uses_the_shipped_one():
    res = quadformer.detect_log(COPTER)
    default = pretrained.resolve("magbaro")
    assert res.detector.zoo_name_ == default.name and res.sensors == "gps+imu+mag+baro"
    assert res.detector.threshold_ == default.card["calibration"]["budget_threshold"]
    assert len(res.scores) == len(res.rows) > 500 and np.isfinite(res.scores).all()
    assert quadformer.pretrained("gps+imu+mag+baro").name == default.method


@pytest.mark.parametrize("log, residues, set_", [
    (COPTER, "ekf", "magbaro"),
    (PX4, "ekf", "magbaro"),
    (PX4, "autopilot", "px4"),
])
def test_detect_runs_without_a_model(log, residues, set_, tmp_path):
    shipped = pretrained.sets()[set_].default
    out = tmp_path / "det"
    res = runner.invoke(app, ["detect", str(log), "--residues", residues, "--out", str(out), "--quiet"])
    assert res.exit_code == 0, res.output
    assert f"detector: shipped {shipped}" in res.output and "chosen for" in res.output
    summary = json.loads((out / log.name / "summary.json").read_text())
    assert summary["model"] == f"shipped:{shipped}"
    assert (out / log.name / "report.html").exists()


def test_detect_over_logs_of_different_sensors_fuses_each_logs_own(tmp_path):
    """A vehicle without a compass beside one with: the shipped default reads the GPS residues
    only, so both are scored, each replay fusing the set's sensors its log has."""
    import dataclasses

    from quadformer.experiments.flight_logs import UTC0
    from quadformer.logs import read_log
    from quadformer.logs.dataflash_writer import write_dataflash
    from quadformer.logs.writing import LogHeader

    logs = tmp_path / "logs"
    logs.mkdir()
    shutil.copy(COPTER, logs / "compass.bin")
    no_mag = dataclasses.replace(read_log(COPTER), mag=None)
    write_dataflash(no_mag, logs / "no_compass.bin", LogHeader(utc0=UTC0))
    out = tmp_path / "det"
    res = runner.invoke(app, ["detect", str(logs), "--out", str(out), "--quiet", "--workers", "1"])
    assert res.exit_code == 0, res.output
    default = pretrained.sets()["magbaro"].default
    assert pretrained.needs(default) == {"gps", "imu"}
    fused = {n: json.loads((out / n / "summary.json").read_text())["sensors"]
             for n in ("compass.bin", "no_compass.bin")}
    assert fused == {"compass.bin": "gps+imu+mag+baro", "no_compass.bin": "gps+imu+baro"}


def test_detect_takes_a_shipped_name_or_set_and_names_what_is_neither(tmp_path):
    res = runner.invoke(app, ["detect", str(COPTER), "--model", "magbaro-cusum-ref", "--out", str(tmp_path / "a"),
                              "--quiet"])
    assert res.exit_code == 0, res.output
    assert "detector: shipped magbaro-cusum-ref (cusum-ref, gps+imu+mag+baro" in res.output
    res = runner.invoke(app, ["detect", str(COPTER), "--model", "magbaro-lstm", "--out", str(tmp_path / "b")])
    assert res.exit_code == 2 and "neither a model file nor a shipped detector" in res.output
    res = runner.invoke(app, ["detect", str(COPTER), "--residues", "autopilot", "--out", str(tmp_path / "c"),
                              "--quiet"])                               # ArduPilot's own innovations
    assert res.exit_code == 0 and "shipped ardupilot-glr (glr), chosen for sim_copter.bin" in res.output


def test_zoo_list_and_show_print_the_cards():
    res = runner.invoke(app, ["zoo", "list"])
    assert res.exit_code == 0, res.output
    for name in pretrained.entries():
        assert name in res.output
    res = runner.invoke(app, ["zoo", "show", "magbaro-quadformer"])
    assert res.exit_code == 0, res.output
    e = pretrained.resolve("magbaro-quadformer")
    for text in ("training data (simulated; no real log)", "seed", "calibration: F1 threshold", "budget threshold",
                 "test:", "versions:", e.files["magbaro-quadformer.pt"][:16]):
        assert text in res.output
    res = runner.invoke(app, ["zoo", "show", "nope"])
    assert res.exit_code == 2 and "no shipped detector 'nope'" in res.output


def test_zoo_build_gives_the_same_files_twice(tmp_path):
    """The px4 set (the NIS tests) built twice from one cache of its simulated flights (10 flights of
    20 s per airframe: a quick trial of the recipe): the same checksums; the index's cards say how
    they were trained."""
    from quadformer.experiments.zoo import build

    cache = tmp_path / "cache"
    a = build(tmp_path / "a", cache, sets=["px4"], flights=10, duration=20.0, progress=False, echo=lambda s: None)
    b = build(tmp_path / "b", cache, sets=["px4"], flights=10, duration=20.0, progress=False, echo=lambda s: None)
    assert {k: v["files"] for k, v in a["detectors"].items()} == {k: v["files"] for k, v in b["detectors"].items()}
    assert list(a["detectors"]) == ["px4-cusum", "px4-chi2"]
    default = a["sets"]["px4"]["default"]
    assert pretrained.load("px4", root=tmp_path / "a").name == a["detectors"][default]["method"]
    card = a["detectors"]["px4-cusum"]["card"]
    assert card["training"]["split"]["train"] == 12 and card["training"]["simulation"][0]["flights"] == 10
    assert card["training"]["simulation"][0]["duration_s"] == 20.0
    assert not list(tmp_path.glob(".*"))     # nothing half-written left beside the outputs
    # a field run's figures go into the cards only when it judged these very files
    from quadformer.experiments.zoo import attach_field

    run = {"shipped": "px4", "shipped_files": {k: v["files"] for k, v in a["detectors"].items()},
           "read": [{"log": "a.bin"}], "refused": [],
           "false_alarms": [{"method": "cusum", "threshold": "sim", "logs": 1, "air_hours": 0.5, "spoofing_air": 2,
                             "per_air_hour": 4.0, "ci_low": 0.5, "ci_high": 14.4}],
           "injection": [{"method": "cusum", "threshold": "sim", "kind": "bias", "injected": 6, "event_recall": 0.5,
                          "recall_big": 0.6, "delay_median_s": 1.0}]}
    (tmp_path / "field.json").write_text(json.dumps(run))
    assert attach_field(a, tmp_path / "field.json") == "px4"
    card = a["detectors"]["px4-cusum"]["card"]["field"]
    assert card["false_alarms_clean"][0]["spoofing_air"] == 2 and card["injected"][0]["event_recall"] == 0.5
    assert a["detectors"]["px4-chi2"]["card"]["field"]["injected"] == []
    run["shipped_files"]["px4-chi2"] = {"px4-chi2.qfm": "0" * 64}
    (tmp_path / "field.json").write_text(json.dumps(run))
    with pytest.raises(ValueError, match="judged other files than the px4 set"):
        attach_field(a, tmp_path / "field.json")
    with pytest.raises(ValueError, match="seed: 0 is a seed benchmarks or the demo test on"):
        build(tmp_path / "c", cache, sets=["px4"], seed=0)
    with pytest.raises(ValueError, match="sets: unknown nope"):
        build(tmp_path / "c", cache, sets=["nope"])
    with pytest.raises(ValueError, match="field: .*nope.json: no such file"):     # before any work
        build(tmp_path / "c", cache, sets=["px4"], field=tmp_path / "nope.json")
    assert not (tmp_path / "c").exists()
    # one method rebuilt, the set's other detector kept: the same files, the rebuild recorded
    c = build(tmp_path / "a", cache, sets=["px4"], methods=["chi2"], flights=10, duration=20.0, progress=False,
              echo=lambda s: None)
    assert {k: v["files"] for k, v in c["detectors"].items()} == {k: v["files"] for k, v in a["detectors"].items()}
    assert list(c["detectors"]) == ["px4-cusum", "px4-chi2"] and c["sets"]["px4"]["default"] == default
    assert [r["methods"] for r in c["sets"]["px4"]["rebuilt"]] == [["chi2"]]
    assert c["sets"]["px4"]["provenance"] == a["sets"]["px4"]["provenance"]
    with pytest.raises(ValueError, match="methods: sprt not in the px4 set; choose from cusum, chi2"):
        build(tmp_path / "a", cache, sets=["px4"], methods=["sprt"])
    with pytest.raises(ValueError, match="methods: name the sets"):
        build(tmp_path / "a", cache, methods=["chi2"])
    with pytest.raises(ValueError, match="px4-cusum was built from other flights than these"):
        build(tmp_path / "a", cache, sets=["px4"], methods=["chi2"], flights=11, duration=20.0, progress=False)
    with pytest.raises(ValueError, match="methods: no px4 set in .* to keep"):
        build(tmp_path / "d", cache, sets=["px4"], methods=["chi2"], flights=10, duration=20.0)
    assert pretrained.index(tmp_path / "a")["sets"]["px4"]["rebuilt"][0]["methods"] == ["chi2"]
