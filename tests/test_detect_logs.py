"""Detection on real flight logs through the CLI, as a user runs it: both residue sources,
a report per log, datasets from logs with injected spoofs, bad input."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from logs_support import FIX
from pyulog import ULog
from typer.testing import CliRunner

from quadformer.cli import app
from quadformer.dataset import load_dataset, write_dataset
from quadformer.detectors import load
from quadformer.detectors.attack_types import SHAPE_TYPES
from quadformer.logs import read_log
from quadformer.logs.dataflash_writer import write_dataflash
from quadformer.logs.replay import autopilot_rows

runner = CliRunner()
EVENTS = FIX / "sample_px4_events.ulg"
COPTER = FIX / "sim_copter.bin"


@pytest.fixture(scope="module")
def models(bias_dataset, tmp_path_factory):
    """chi2 (reads the NIS only) and an SVM (reads every residue group) fit on simulated flights."""
    d = tmp_path_factory.mktemp("models")
    data = write_dataset(bias_dataset, d / "ds")
    out = {}
    for method in ("chi2", "svm"):
        res = runner.invoke(app, ["fit", "--method", method, "--data", str(data), "--label-fraction", "1",
                                  "--out", str(d / f"{method}.json")])
        assert res.exit_code == 0, res.output
        out[method] = d / f"{method}.json"
    return out


def test_autopilot_residues_are_the_logged_innovations_flipped_and_whitened():
    log = read_log(EVENTS)
    rows = autopilot_rows(log)
    inn = log.innovations.set_index("t").loc[rows.t]
    # measured minus predicted: PX4 logs predicted minus measured (ENU after the reader)
    np.testing.assert_allclose(rows.res_gps_r_px, -inn.pos_x.to_numpy())
    np.testing.assert_allclose(rows.res_gps_r_vy, -inn.vel_y.to_numpy())
    fused = inn.var_pos_x.to_numpy() > 0
    np.testing.assert_allclose(rows.res_gps_w_px[fused], -inn.pos_x[fused] / np.sqrt(inn.var_pos_x[fused]))
    w = rows[[f"res_gps_w_{a}" for a in ("px", "py", "pz", "vx", "vy", "vz")]].to_numpy()
    np.testing.assert_allclose(rows.res_gps_nis, (w * w).sum(1))
    # the samples before the autopilot fused any fix (innovations against an unset fix) are left out
    assert rows.t.iloc[0] >= log.gps.t.iloc[0] and np.abs(rows.res_gps_r_px).max() < 1.0
    assert np.isfinite(rows.filter(like="res_").to_numpy()).all()
    # ArduPilot logs no variances: whitened by those recovered from XKF4's test ratios
    copter = read_log(COPTER)
    rows = autopilot_rows(copter)
    inn = copter.innovations.set_index("t").loc[rows.t]
    fused = inn.var_vel_x.to_numpy() > 0
    np.testing.assert_allclose(rows.res_gps_w_vx[fused], -inn.vel_x[fused] / np.sqrt(inn.var_vel_x[fused]))
    np.testing.assert_allclose(rows.res_gps_nis, (rows.filter(regex="res_gps_w_") ** 2).sum(axis=1))
    assert np.isfinite(rows.filter(like="res_").to_numpy()).all()


def test_detect_with_autopilot_residues_writes_scores_alerts_and_a_report(models, tmp_path):
    out = tmp_path / "det"
    res = runner.invoke(app, ["detect", str(EVENTS), "--model", str(models["chi2"]), "--residues", "autopilot",
                              "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "alert(s)" in res.output and "autopilot residues" in res.output
    folder = out / EVENTS.name
    scores = pd.read_csv(folder / "scores.csv")
    det = load(models["chi2"])
    rows = autopilot_rows(read_log(EVENTS))
    np.testing.assert_allclose(scores.score, det.decision_function(rows))
    assert np.array_equal(scores.alarm, (scores.score > det.threshold_).astype(int))
    summary = json.loads((folder / "summary.json").read_text())
    assert summary["steps"] == len(rows) and summary["residues"] == "autopilot"
    html = (folder / "report.html").read_text()
    assert html.count("data:image/png;base64,") >= 3 and "sample_px4_events.ulg" in html
    assert set(pd.read_csv(out / "alerts.csv").columns) >= {"log", "flight_id", "start_s", "attack_type"}


def test_detect_refuses_a_detector_whose_residues_the_source_cannot_provide(models, tmp_path):
    res = runner.invoke(app, ["detect", str(EVENTS), "--model", str(models["svm"]), "--residues", "autopilot",
                              "--out", str(tmp_path / "o")])
    assert res.exit_code == 2
    assert "reads res_gps_corr" in res.output and "do not provide" in res.output and "--residues ekf" in res.output
    assert res.output.count(str(EVENTS)) == 1                       # the path once
    assert "simulate --sensors" not in res.output                   # one remedy: the model's own sensors are not it
    assert not (tmp_path / "o" / EVENTS.name).exists()
    # a DataFlash log whose test ratios are all 0 (none known when written) holds no variance: no NIS
    log = read_log(COPTER)
    blank = log.innovations.copy()
    blank.loc[:, blank.columns.str.startswith(("var_", "ratio_"))] = np.nan
    path = write_dataflash(dataclasses.replace(log, innovations=blank), tmp_path / "no_ratios.bin")
    res = runner.invoke(app, ["detect", str(path), "--model", str(models["chi2"]), "--residues", "autopilot",
                              "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "reads res_gps_nis" in res.output
    assert any("hold no variance" in n for n in read_log(path).notes)
    res = runner.invoke(app, ["detect", str(COPTER), "--model", str(models["chi2"]), "--residues", "autopilot",
                              "--out", str(tmp_path / "o"), "--quiet"])
    assert res.exit_code == 0, res.output


def test_detect_over_a_directory_keeps_going_past_a_bad_log(models, tmp_path):
    logs = tmp_path / "logs"
    logs.mkdir()
    shutil.copy(EVENTS, logs / "good.ulg")
    (logs / "bad.ulg").write_bytes(EVENTS.read_bytes()[:2000])      # truncated inside the header
    (logs / "notes.txt").write_text("not a log")
    out = tmp_path / "det"
    res = runner.invoke(app, ["detect", str(logs), "--model", str(models["chi2"]), "--residues", "autopilot",
                              "--out", str(out), "--quiet"])
    assert res.exit_code == 1, res.output                          # one of two logs failed
    assert "bad.ulg" in res.output and "1 of 2 log(s) could not be processed" in res.output
    assert (out / "good.ulg" / "report.html").exists() and not (out / "bad.ulg").exists()
    assert not list(out.glob(".*"))                                # no temporary leftovers
    assert pd.read_csv(out / "summary.csv").log.tolist() == [str(logs / "good.ulg")]


@pytest.mark.parametrize("args, message", [
    (["detect", str(EVENTS), "--model", "/nonexistent.json"], "no such model file"),
    (["detect", "/nonexistent.ulg", "--model", "M"], "no such file or directory"),
    (["detect", str(EVENTS), "--model", "M", "--residues", "magic"], "unknown source 'magic'"),
    (["detect", str(EVENTS), "--model", "M", "--format", "dji"], "unknown format 'dji'"),
    (["detect", str(EVENTS), "--model", "M", "--typing", "labels"], "typing: unknown 'labels'"),
    (["detect", str(EVENTS), "--model", "M", "--gps-rate", "0"], "gps_rate_hz must be a positive number"),
    (["logs", "import", str(EVENTS), "--out", "D", "--inject", "jamming"], "unknown attack 'jamming'"),
    (["logs", "info", str(FIX / "make_rosbags.py")], "unknown log format"),
])
def test_bad_input_is_named(args, message, models, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    args = [str(models["chi2"]) if a == "M" else a for a in args]
    res = runner.invoke(app, args)
    assert res.exit_code == 2, res.output
    assert message in res.output


def test_benchmark_on_given_datasets(bias_dataset, tmp_path):
    a = write_dataset(bias_dataset, tmp_path / "fleet-a")
    b = write_dataset(bias_dataset, tmp_path / "fleet-b")
    out = tmp_path / "bench"
    res = runner.invoke(app, ["benchmark", "--data", str(a), "--data", str(b), "--methods", "chi2,cusum",
                              "--out", str(out), "--quiet"])
    assert res.exit_code == 0, res.output
    assert "fleet-a-F1" in res.output
    r = json.loads((out / "results.json").read_text())
    assert r["profile"] is None and [c["name"] for c in r["configs"]] == ["fleet-a", "fleet-b"]
    # the same data and protocol give the same figures
    assert r["configs"][0]["methods"]["cusum"]["f1"] == r["configs"][1]["methods"]["cusum"]["f1"]
    table = pd.read_csv(out / "table_datasets.csv", index_col=0)
    assert list(table.index) == ["chi2", "cusum"] and table.shape[1] == 6
    assert "data:image/png;base64," in (out / "report.html").read_text()
    res = runner.invoke(app, ["benchmark", "--data", str(tmp_path / "nope"), "--out", str(out)])
    assert res.exit_code == 2 and "no such dataset directory" in res.output


def test_detect_on_damaged_logs_ends_in_a_result_or_a_named_error(models, tmp_path):
    """Seeded truncations and byte flips of a real log through `detect`: each run ends with
    exit 0 and a complete output folder, or exit 2, a named error and no folder at all."""
    rng = np.random.default_rng(7)
    data = EVENTS.read_bytes()
    outcomes = {0: 0, 2: 0}
    for case in range(20):
        buf = bytearray(data)
        if case % 2:
            buf = buf[: int(rng.integers(100, len(buf)))]
        else:
            for i in rng.integers(len(buf) // 50, len(buf), size=20):
                buf[i] ^= 0xFF
        path = tmp_path / f"case{case}.ulg"
        path.write_bytes(bytes(buf))
        out = tmp_path / f"out{case}"
        res = runner.invoke(app, ["detect", str(path), "--model", str(models["chi2"]), "--residues", "autopilot",
                                  "--out", str(out), "--quiet"])
        assert res.exit_code in (0, 2), (case, res.output, res.exception)
        assert "Traceback" not in res.output
        outcomes[res.exit_code] += 1
        folder = out / path.name
        if res.exit_code == 0:                                 # scored, or readable with nothing to score
            names = {p.name for p in folder.iterdir()}
            scored = json.loads((folder / "summary.json").read_text()).get("scored", True)
            assert names == ({"report.html", "scores.csv", "alerts.csv", "summary.json"} if scored
                             else {"report.html", "summary.json"})
        else:
            assert "case" in res.output and not folder.exists()
        assert not out.exists() or not list(out.glob(".*"))       # no temporary leftovers
    assert outcomes[0] > 0 and outcomes[2] > 0


def test_replaying_a_simulated_flight_from_a_ros_bag_recovers_the_simulators_residues():
    """The ROS bag fixture holds a simulated flight's sensors (IMU, GPS, odometry). Replayed
    with the simulation's own filter tuning, the GPS innovations follow the ones the
    simulator's filter produced in the loop (the replay starts at the first fix instead of the
    simulator's initial state, so they agree once both have converged)."""
    from quadformer.config import SimConfig
    from quadformer.estimator.online import FilterConfig
    from quadformer.logs.replay import ekf_rows
    from quadformer.simulation import simulate_batch

    cfg = SimConfig(flights=1, duration=12.0, seed=5)          # the flight the fixture was written from
    sim = simulate_batch(cfg, np.arange(1), np.zeros(1, bool))
    flight = ekf_rows(read_log(FIX / "sim_flight_ros1.bag"), config=FilterConfig.matching(cfg.to_dict()))
    assert flight.sensors == "gps+imu+vio"
    rows = flight.rows
    late = sim["t"] > 4.0
    nis = np.interp(sim["t"], rows.t + 0.012, rows.res_gps_nis)   # bag times start at its first message
    assert np.corrcoef(nis[late], sim["res_gps_nis"][0, late, 0])[0, 1] > 0.95
    assert abs(nis[late].mean() / sim["res_gps_nis"][0, late, 0].mean() - 1) < 0.1
    r_px = np.interp(sim["t"], rows.t + 0.012, rows.res_gps_r_px)
    assert np.abs(r_px - sim["res_gps_r"][0, :, 0])[late].max() < 0.3          # m, of an innovation rms 0.45 m


def test_the_simulations_tuning_trusts_a_receiver_as_little_as_it_states(models, tmp_path):
    """``sample_log_small.ulg`` is a real flight whose receiver states 2.8 m / 5.9 m of position
    error (eph / epv, medians), where the default simulation's GPS has 0.5 m of white noise.
    Replayed with that simulation's tuning (what ``detect --filter model`` uses for a model fit
    on it), each fix is weighted by the larger of the simulated noise and the receiver's stated
    accuracy, as the autopilot weights it: the clean flight's NIS stays below 5. With the
    simulated noise alone the receiver's own error reads as a spoof (NIS above 10, and every
    simulation-trained detector alerted on this clean log)."""
    from quadformer.config import SimConfig
    from quadformer.estimator.online import FilterConfig
    from quadformer.logs.replay import ekf_rows

    log = read_log(FIX / "sample_log_small.ulg")
    assert log.gps.eph.median() > 2.5
    sim = SimConfig(sensors="gps+imu+mag+baro").to_dict()
    stated = ekf_rows(log, config=FilterConfig.matching(sim)).rows
    assert stated.res_gps_nis.max() < 5.0
    floor = ekf_rows(log, config=FilterConfig.matching(sim, receiver_accuracy=False)).rows
    assert floor.res_gps_nis.max() > 10.0
    # as a user runs it: the NIS test fit on simulated flights, on the clean log, both ways
    peak = {}
    for flag in ("--receiver-accuracy", "--no-receiver-accuracy"):
        res = runner.invoke(app, ["detect", str(FIX / "sample_log_small.ulg"), "--model", str(models["chi2"]),
                                  flag, "--out", str(tmp_path / flag), "--quiet"])
        assert res.exit_code == 0, res.output
        peak[flag] = pd.read_csv(tmp_path / flag / "sample_log_small.ulg" / "scores.csv").score.max()
    assert peak["--no-receiver-accuracy"] > 3.0 * peak["--receiver-accuracy"], peak


def test_a_fix_is_fused_at_its_measurement_time_the_autopilots_gps_delay_before_its_stamp():
    """A receiver's fix is measured before it is stamped. On the PX4 SITL log the vehicle takes
    off at 19 s: fused at its stamp, each fix's vertical velocity lags the IMU's and the
    innovation reaches 0.22 m/s; fused at its measurement time, EKF2_GPS_DELAY (110 ms, read
    from the log) earlier, it halves (and at 200 ms almost vanishes: this receiver's latency).
    The filter runs that far behind the newest IMU sample; rows keep the fixes' stamps."""
    from quadformer.config import SimConfig
    from quadformer.estimator.online import FilterConfig
    from quadformer.logs.replay import ekf_rows

    log = read_log(EVENTS)
    sim = SimConfig(sensors="gps+imu+mag+baro").to_dict()
    runs = {d: ekf_rows(log, config=FilterConfig.matching(sim, gps_delay_s=d)) for d in (0.0, None, 0.2)}
    assert any("fused 110 ms before its stamp" in n for n in runs[None].notes)
    assert not any("before its stamp" in n for n in runs[0.0].notes)
    take_off = {d: f.rows[(f.rows.t > 18.5) & (f.rows.t < 21.5)].res_gps_r_vz.abs().max() for d, f in runs.items()}
    assert take_off[0.0] > 0.15
    assert take_off[None] < 0.6 * take_off[0.0] and take_off[0.2] < 0.2 * take_off[0.0]
    for f in runs.values():
        np.testing.assert_array_equal(f.rows.t, runs[0.0].rows.t)
    with pytest.raises(ValueError, match="gps_delay_s"):
        FilterConfig(gps_delay_s=0.9)


def test_detect_with_the_replayed_filter_on_px4_and_ardupilot_logs(models, tmp_path):
    out = tmp_path / "det"
    res = runner.invoke(app, ["detect", str(EVENTS), str(COPTER), "--model", str(models["chi2"]),
                              "--out", str(out), "--quiet"])
    assert res.exit_code == 0, res.output
    for log in (EVENTS, COPTER):
        s = json.loads((out / log.name / "summary.json").read_text())
        assert s["residues"] == "ekf" and s["sensors"] == "gps+imu+mag+baro"
        rows = pd.read_csv(out / log.name / "scores.csv")
        assert {"res_gps_nis", "res_mag_r_yaw", "res_baro_r_z", "est_pos_x", "ap_pos_x"} <= set(rows.columns)
        assert not any(c.startswith("res_vio") for c in rows.columns)
        # the replayed estimate follows the autopilot's own (both fuse the same fixes)
        gap = np.hypot(rows.est_pos_x - rows.ap_pos_x, rows.est_pos_y - rows.ap_pos_y)
        assert np.median(gap) < 1.0
        html = (out / log.name / "report.html").read_text()
        assert "autopilot's estimate" in html or "autopilot" in html
        # t counts from the log's first sensor sample, as the live monitor does; boot time beside
        read = read_log(log)
        assert min(float(df.t.iloc[0]) for n, df in read.streams.items()
                   if n in ("imu", "gps", "mag", "baro", "odometry", "attitude")) == 0.0
        assert s["boot_t0_s"] == pytest.approx(read.boot_t0) and read.boot_t0 > 0
        np.testing.assert_allclose(rows.boot_t - rows.t, read.boot_t0, atol=1e-6)
    imu = ULog(str(EVENTS), ["sensor_combined"]).data_list[0].data["timestamp"]
    read = read_log(EVENTS)                         # the vehicle's clock is t + boot_t0
    assert read.boot_t0 + float(read.imu.t.iloc[0]) == pytest.approx(imu[0] * 1e-6, abs=1e-6)
    # a detector fit with VIO residues refuses a log without a camera, and says what would help
    res = runner.invoke(app, ["detect", str(COPTER), "--model", str(models["svm"]), "--out", str(tmp_path / "x")])
    assert res.exit_code == 2 and "res_vio_r" in res.output and "--sensors gps+imu+mag+baro" in res.output


def test_detect_on_several_cores_writes_what_one_core_writes(models, tmp_path):
    """Two worker processes (spawned, one log each at a time) against one after the other in
    this process: the same scores, alerts and summaries, in the order of the logs given."""
    logs = [str(EVENTS), str(COPTER), str(FIX / "sample_log_small.ulg")]
    for workers in (1, 2):
        res = runner.invoke(app, ["detect", *logs, "--model", str(models["chi2"]), "--out",
                                  str(tmp_path / f"w{workers}"), "--quiet", "--workers", str(workers)])
        assert res.exit_code == 0, res.output
    one, two = tmp_path / "w1", tmp_path / "w2"
    pd.testing.assert_frame_equal(pd.read_csv(one / "summary.csv"), pd.read_csv(two / "summary.csv"))
    assert pd.read_csv(two / "summary.csv")["log"].tolist() == logs
    pd.testing.assert_frame_equal(pd.read_csv(one / "alerts.csv"), pd.read_csv(two / "alerts.csv"))
    for log in logs:
        name = Path(log).name
        pd.testing.assert_frame_equal(pd.read_csv(one / name / "scores.csv"), pd.read_csv(two / name / "scores.csv"))
    res = runner.invoke(app, ["detect", str(EVENTS), "--model", str(models["chi2"]), "--workers", "-1"])
    assert res.exit_code == 2 and "--workers must be 0" in res.output


def test_log_alerts_are_raised_by_the_online_step_as_by_the_batch_tracker():
    """detect_log drives each segment's rows through resilience.step.OnlineStep (the live
    monitor's and the closed loop's step): the alerts equal the batch tracker's over the scores."""
    from quadformer import make
    from quadformer.detectors import alerts_from_scores
    from quadformer.detectors.attack_types import alert_typer
    from quadformer.logs.detect import log_rows, step_alerts

    flights, _ = log_rows(read_log(COPTER))
    rows = pd.concat([f.rows for f in flights], ignore_index=True)
    for name in ("chi2", "cusum"):
        det = make(name).fit(rows, np.zeros(len(rows), np.int8))
        scores = det.decision_function(rows)
        det.calibrate(float(np.quantile(scores, 0.97)), float(np.quantile(scores, 0.99)))
        batch = alerts_from_scores(rows, scores, det, typer=alert_typer(rows, "shape"))
        assert batch and step_alerts(rows, scores, det, "shape") == batch, name
        assert all(a.confirmed_type is not None for a in batch)


def test_logs_import_injects_labelled_spoofs_the_residues_see(models, tmp_path):
    ds_dir = tmp_path / "fleet"
    res = runner.invoke(app, ["logs", "import", str(EVENTS), str(COPTER), "--out", str(ds_dir), "--inject", "bias",
                              "--magnitude", "4,6", "--onset", "5,8", "--attack-duration", "8,10",
                              "--attack-fraction", "0.5", "--repeat", "4", "--seed", "3"])
    assert res.exit_code == 0, res.output
    ds = load_dataset(ds_dir)
    sc = ds.scenarios
    assert len(sc) == 8 and sc.attacked.sum() == 4 and sc.group.nunique() == 2
    assert ds.gps_rate_hz == 10.0 and ds.meta["source"] == "logs"
    f = ds.flights
    for _, s in sc.iterrows():
        g = f[f.flight_id == s.flight_id]
        lab = g.label.to_numpy() == 1
        assert lab.any() == s.attacked
        if s.attacked:
            t0 = g.t.iloc[0] - 0.1                  # the first fix initialises the filter
            assert s.onset == pytest.approx(g.t[lab].iloc[0] - t0, abs=0.25)
            d = np.linalg.norm(g[["atk_d_x", "atk_d_y", "atk_d_z"]].to_numpy()[lab], axis=1)
            assert np.allclose(d, s.magnitude)
            # the spoofed fixes are the logged ones plus the offset; the filter's innovations jump
            assert g.res_gps_nis[lab].iloc[0] > 20 * np.median(g.res_gps_nis[~lab])
    # the clean repetitions of one segment are identical (same recording, no injection)
    clean = sc[~sc.attacked]
    for _, group in clean.groupby("group"):
        ids = group.flight_id.to_numpy()
        if len(ids) > 1:
            a, b = (f[f.flight_id == i].res_gps_nis.to_numpy() for i in ids[:2])
            assert np.array_equal(a, b)
    out = tmp_path / "eval"
    res = runner.invoke(app, ["evaluate", "--model", str(models["chi2"]), "--data", str(ds_dir), "--out", str(out)])
    assert res.exit_code == 0, res.output
    r = json.loads((out / "results.json").read_text())
    assert r["metrics"]["event_recall"] > 0.5
    # alerts typed by shape from the logs' own reference residues (IMU + barometer, no camera)
    alerts = pd.read_csv(out / "alerts.csv")
    assert len(alerts) and set(alerts.attack_type) <= set(SHAPE_TYPES)
    res = runner.invoke(app, ["evaluate", "--model", str(models["chi2"]), "--data", str(ds_dir), "--out",
                              str(tmp_path / "own"), "--typing", "detector"])
    assert res.exit_code == 0, res.output
    assert set(pd.read_csv(tmp_path / "own" / "alerts.csv").attack_type) == {"attack"}   # chi2 does not classify


def test_a_log_without_gps_gets_a_report_saying_why(models, tmp_path):
    out = tmp_path / "det"
    res = runner.invoke(app, ["detect", str(FIX / "sample.ulg"), "--model", str(models["chi2"]), "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "nothing scored" in res.output and "no GPS fixes" in res.output and "--residues" not in res.output
    s = json.loads((out / "sample.ulg" / "summary.json").read_text())
    assert s["scored"] is False and "no GPS" in s["reason"]
    assert "Nothing scored" in (out / "sample.ulg" / "report.html").read_text()
    # the other residue source says the same, instead of sending the user back
    res = runner.invoke(app, ["detect", str(FIX / "sample.ulg"), "--model", str(models["chi2"]), "--residues",
                              "autopilot", "--out", str(tmp_path / "ap")])
    assert "no GPS fixes" in res.output and "--residues" not in res.output and res.output.count("sample.ulg") == 1


def test_calibrate_sets_the_threshold_from_a_vehicles_clean_logs_at_a_false_alarm_budget(models, tmp_path):
    """`quadformer calibrate`: the model's threshold from the vehicle's own clean logs at the budget,
    what it was calibrated on recorded, and the leave-one-log-out false-alarm estimate printed."""
    small = FIX / "sample_log_small.ulg"
    out = tmp_path / "vehicle.json"
    res = runner.invoke(app, ["calibrate", "--clean", str(EVENTS), "--clean", str(small), "--model",
                              str(models["chi2"]), "--budget", "1/h", "--residues", "autopilot", "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "leaving one log out:" in res.output and "per hour (95% interval" in res.output
    before, after = load(models["chi2"]), load(out)
    cal = after.calibration_
    assert list(cal["vehicle_logs"]) == [str(EVENTS), str(small)] and cal["false_alarm_budget_per_hour"] == 1.0
    assert cal["before_vehicle"]["threshold"] == before.threshold_ and after.threshold_ != before.threshold_
    lo, hi = cal["held_out_interval"]
    assert 0.0 <= lo <= cal["held_out_alarms_per_hour"] <= hi
    # under a minute of flight allows no alarm run at 1 per hour: none on these logs at the new threshold
    det = runner.invoke(app, ["detect", str(EVENTS), str(small), "--model", str(out), "--residues", "autopilot",
                              "--out", str(tmp_path / "det"), "--quiet"])
    assert det.exit_code == 0, det.output
    assert len(pd.read_csv(tmp_path / "det" / "alerts.csv")) == 0
    # bad input is named
    bad = runner.invoke(app, ["calibrate", "--clean", str(EVENTS), "--model", str(models["chi2"]), "--budget", "often",
                              "--out", str(tmp_path / "x.json")])
    assert bad.exit_code == 2 and "--budget" in bad.output
    one = runner.invoke(app, ["calibrate", "--clean", str(EVENTS), "--model", str(models["chi2"]), "--residues",
                              "autopilot", "--out", str(tmp_path / "x.json")])
    assert one.exit_code == 2 and "at least 2" in one.output and not (tmp_path / "x.json").exists()


def test_logs_info_gives_the_physical_floor():
    from quadformer.logs.noise import detection_floor
    from quadformer.logs.replay import in_air

    assert "physical floor" not in runner.invoke(app, ["logs", "info", str(COPTER)]).output
    res = runner.invoke(app, ["logs", "info", str(COPTER), "--floor"])
    assert res.exit_code == 0, res.output
    log = read_log(COPTER)
    f = detection_floor(log, in_air(log, log.gps["t"].to_numpy()) > 0.5)
    assert f"consistent drift {f.drift_ms:.2f} m/s ({f.drift_tail_ms:.2f} m/s with its tails)" in res.output
    assert f"over {f.intervals} GPS intervals in the air" in res.output
    res = runner.invoke(app, ["logs", "info", str(EVENTS), "--floor"])   # no attitude in the air: said, no crash
    assert res.exit_code == 0 and "physical floor: not computed" in res.output
