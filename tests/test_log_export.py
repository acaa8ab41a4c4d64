"""Simulated flights exported as PX4 ULog and ArduPilot DataFlash logs, read back.

Two 5 s flights (one spoofed from 2-3 s on), every sensor configured, exported through
``simulate(on_batch=LogExport(...))`` as ``simulate --export`` does. Read back with the
project's readers, every stream equals the simulator's arrays within the formats'
quantisation (DataFlash: 1e-7 deg latitude/longitude, cm altitudes, innovations and
accuracies, centidegree angles, milligauss, square roots of test ratios to 0.01; float32
elsewhere); pyulog and pymavlink open the files and count the messages written; ``detect``
scores the files from both residue sources.
"""

from __future__ import annotations

import collections
import json

import numpy as np
import pandas as pd
import pytest
from pymavlink import DFReader
from pyulog import ULog
from typer.testing import CliRunner

from quadformer.cli import app
from quadformer.config import AttackConfig, SimConfig
from quadformer.dataset import load_dataset
from quadformer.detectors import make
from quadformer.experiments.flight_logs import BOOT_T0, ORIGIN, LogExport, export_formats
from quadformer.geometry import frames
from quadformer.logs import read_log
from quadformer.logs.detect import log_rows
from quadformer.logs.replay import autopilot_rows
from quadformer.simulation import simulate

runner = CliRunner()
SUFFIX = {"ulog": ".ulg", "dataflash": ".bin"}
CFG = SimConfig(flights=2, duration=5.0, seed=5, sensors="gps+imu+vio+mag+baro",
                attack=AttackConfig(kind="bias", fraction=0.5, onset=(2.0, 3.0), magnitude=(4.0, 6.0)))

#: ArduPilot's test ratio groups: the simulator's GPS residue columns (position x, y, z, velocity x, y, z) each sums
GROUPS = {"pos": [0, 1], "hgt": [2], "vel": [3, 4, 5]}

# (atol) per format: the formats' quantisation, and float32 elsewhere
TOL = {
    "dataflash": {"imu": 1e-5, "gps_pos": 0.006, "gps_vel": 1e-5, "baro": 1e-4, "mag": 5.1e-4, "att_deg": 0.01,
                  "estimate": 1e-4, "innovation": 0.0051, "ratio_root": 0.0051, "truth_pos": 0.006,
                  "vel": 1e-5, "odometry": 1e-4},
    "ulog": {"imu": 1e-5, "gps_pos": 1e-6, "gps_vel": 1e-5, "baro": 1e-4, "mag": 1e-6, "att_deg": 1e-4,
             "estimate": 1e-4, "innovation": 1e-5, "ratio_root": 1e-5, "truth_pos": 1e-4, "vel": 1e-5,
             "odometry": 1e-4},
}


@pytest.fixture(scope="module")
def export(tmp_path_factory):
    """(batch result, dataset, logs directory) of CFG, its flights exported both ways."""
    logs = tmp_path_factory.mktemp("export") / "logs"
    batches = []
    writer = LogExport(CFG, logs, ("ulog", "dataflash"))

    def on_batch(r):
        batches.append(r)
        writer(r)
    ds = simulate(CFG, on_batch=on_batch)
    assert len(batches) == 1
    return batches[0], ds, logs


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation angle (deg) between (x, y, z, w) quaternions."""
    dot = np.abs((frames.quat_normalize(a) * frames.quat_normalize(b)).sum(-1))
    return np.degrees(2 * np.arccos(np.clip(dot, 0.0, 1.0)))


def _np(x) -> np.ndarray:
    return x.numpy() if hasattr(x, "numpy") else np.asarray(x)


@pytest.mark.parametrize("fmt", ["dataflash", "ulog"])
@pytest.mark.parametrize("i", [0, 1])
def test_exported_streams_read_back_as_simulated(fmt, i, export):
    r, _, logs = export
    s, tol = r["sensors"], TOL[fmt]
    log = read_log(logs / f"flight_{i:04d}{SUFFIX[fmt]}")
    assert set(log.streams) == {"imu", "gps", "odometry", "baro", "mag", "innovations", "estimate", "attitude",
                                "truth", "receiver"}
    # the flight starts airborne: armed and taken off at the log's first sample, as its events say
    ev = log.events
    assert {"armed", "takeoff"} <= set(ev["event"]) and ev["t"].min() < 1.0
    assert (log.receiver["fix_type"] >= 3).all() and len(log.receiver) >= len(log.gps)
    assert log.origin == pytest.approx(ORIGIN, abs=1e-9) and log.origin_source == "autopilot local origin"

    def sim_t(stream: str, t_sim) -> None:        # the vehicle's clock: BOOT_T0 + simulated time
        df = getattr(log, stream)
        np.testing.assert_allclose(df.t + log.boot_t0, BOOT_T0 + np.asarray(t_sim), atol=1e-6, rtol=0)

    def close(stream: str, cols: list[str], want, atol: float) -> None:
        np.testing.assert_allclose(getattr(log, stream)[cols].to_numpy(), np.asarray(want, dtype=float),
                                   atol=atol, rtol=0, err_msg=f"{fmt} {stream} {cols}")

    for stream, key in (("imu", "imu_t"), ("gps", "gps_t"), ("baro", "baro_t"), ("mag", "mag_t"),
                        ("odometry", "vio_t"), ("attitude", "gps_t"), ("estimate", "gps_t"),
                        ("innovations", "gps_t"), ("truth", "gps_t")):
        sim_t(stream, s[key])
    close("imu", ["ax", "ay", "az", "gx", "gy", "gz"], _np(s["imu"][i]), tol["imu"])
    gps = _np(s["gps"][i])                          # the fixes as received (spoofed on flight 0)
    close("gps", ["x", "y", "z"], gps[:, :3], tol["gps_pos"])
    close("gps", ["vx", "vy", "vz"], gps[:, 3:], tol["gps_vel"])
    # PX4 logs barometric altitude above sea level, ArduPilot above its ground calibration (the origin)
    close("baro", ["alt"], _np(s["baro"][i]) + (ORIGIN[2] if fmt == "ulog" else 0.0), tol["baro"])
    close("mag", ["mx", "my", "mz"], _np(s["mag"][i]), tol["mag"])
    vio = _np(s["vio"][i])
    close("odometry", ["vx", "vy", "vz"], vio[:, :3], tol["odometry"])
    assert _angle_deg(log.odometry[["qx", "qy", "qz", "qw"]].to_numpy(), vio[:, 3:]).max() < tol["att_deg"]
    assert _angle_deg(log.attitude[["qx", "qy", "qz", "qw"]].to_numpy(), _np(s["est_q"][i])).max() < tol["att_deg"]
    close("estimate", ["x", "y", "z"], r["est_pos"][i], tol["estimate"])
    close("estimate", ["vx", "vy", "vz"], r["est_vel"][i], tol["vel"])
    close("truth", ["x", "y"], r["true_pos"][i][:, :2], tol["truth_pos"])
    close("truth", ["z"], r["true_pos"][i][:, 2:], 1e-4)                     # float32 altitude above sea level
    close("truth", ["vx", "vy", "vz"], r["true_vel"][i], tol["vel"])
    assert _angle_deg(log.truth[["qx", "qy", "qz", "qw"]].to_numpy(), _np(s["true_q"][i])).max() < tol["att_deg"]
    # the autopilots log predicted minus measured; the simulator records measured minus predicted
    close("innovations", ["pos_x", "pos_y", "pos_z", "vel_x", "vel_y", "vel_z"], -r["res_gps_r"][i],
          tol["innovation"])
    var = r["res_gps_s"][i] ** 2
    root = np.sqrt(log.innovations[["ratio_pos", "ratio_vel", "ratio_hgt"]].to_numpy())
    if fmt == "ulog":           # PX4: per axis innovation^2 / (5^2 variance), the largest of a group read
        ratio = r["res_gps_r"][i] ** 2 / (25.0 * var)
        want = np.sqrt(np.column_stack([ratio[:, :2].max(1), ratio[:, 3:].max(1), ratio[:, 2]]))
        close("innovations", [f"var_{g}_{a}" for g in ("pos", "vel") for a in "xyz"], var, 1e-6)
    else:                       # ArduPilot: summed squares over summed variances and 5^2 (no variances logged)
        summed = {g: (r["res_gps_r"][i][:, c] ** 2).sum(1) / (25.0 * var[:, c].sum(1)) for g, c in GROUPS.items()}
        want = np.sqrt(np.column_stack([summed["pos"], summed["vel"], summed["hgt"]]))
    np.testing.assert_allclose(root, want, atol=tol["ratio_root"], rtol=0)
    assert not log.estimate["reset"].any() and len(log.segments) == 1


@pytest.mark.parametrize("i", [0, 1])
def test_autopilot_residues_of_the_exported_logs_give_back_the_in_loop_nis(i, export):
    """The autopilot residues of a written log against the in-loop filter's own GPS residues at the
    same steps. PX4 logs the variances: the NIS over them is the in-loop filter's sum over axes of
    (r / s)^2 to float32, and the per-axis test ratios written are PX4's, innovation^2 / (5^2
    variance). ArduPilot logs none: its variances are recovered from the test ratios, each group's
    summed variance shared equally by its axes, so a group's NIS, n 5^2 ratio, gives back the
    in-loop filter's n sum(r^2) / sum(s^2) to the square roots' 0.01 quantisation (a group whose
    ratio or innovations round to 0 is left out: then it was under the quantum). Over all groups
    the equal share and the quantisation keep the NIS within 5% in median and 15% at every step of
    both the in-loop per-axis sum and its NIS over the full innovation covariance, r^T S^-1 r."""
    r, _, logs = export
    ins, s = r["res_gps_r"][i], r["res_gps_s"][i]
    diag = ((ins / s) ** 2).sum(1)
    full = np.asarray(r["res_gps_nis"][i], dtype=float).ravel()
    t_gps = np.asarray(r["sensors"]["gps_t"], dtype=float)
    for fmt in ("ulog", "dataflash"):
        log = read_log(logs / f"flight_{int(r['flights'][i]):04d}{SUFFIX[fmt]}")
        rows = autopilot_rows(log)
        k = np.searchsorted(t_gps, rows["t"].to_numpy() + log.boot_t0 - BOOT_T0 - 1e-6)
        np.testing.assert_allclose(t_gps[k], rows["t"] + log.boot_t0 - BOOT_T0, atol=1e-5)
        nis = rows["res_gps_nis"].to_numpy()
        if fmt == "ulog":
            np.testing.assert_allclose(rows.filter(regex="res_gps_s_").to_numpy(), s[k], rtol=1e-6)
            np.testing.assert_allclose(nis, diag[k], rtol=1e-4)
            written = ULog(str(log.path), ["estimator_innovation_test_ratios"]).data_list[0].data
            for fields, c in ((("gps_hpos[0]", "gps_hpos[1]", "gps_vpos"), [0, 1, 2]),
                              (("gps_hvel[0]", "gps_hvel[1]", "gps_vvel"), [3, 4, 5])):
                got = np.column_stack([written[f] for f in fields])                   # N, E, D
                want = frames.ned_var_to_enu(ins[:, c] ** 2 / (25.0 * s[:, c] ** 2))  # E, N, U -> N, E, D
                np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-12)
            continue
        w = rows.filter(regex="res_gps_w_").to_numpy()
        for g, c in GROUPS.items():
            truth = np.sqrt((ins[k][:, c] ** 2).sum(1) / (25.0 * (s[k][:, c] ** 2).sum(1)))
            got = np.sqrt((w[:, c] ** 2).sum(1) / (len(c) * 25.0))
            fused = rows[{"pos": "res_gps_s_px", "hgt": "res_gps_s_pz", "vel": "res_gps_s_vx"}[g]].to_numpy() > 0
            np.testing.assert_allclose(got[fused], truth[fused], atol=0.0051, rtol=0)
            tiny = (truth < 0.0051) | (np.abs(ins[k][:, c]) < 0.0051).all(1)
            assert tiny[~fused].all() and fused.mean() > 0.9, g
        rel_diag, rel_full = np.abs(nis / diag[k] - 1), np.abs(nis / full[k] - 1)
        for rel in (rel_diag, rel_full):                # measured: medians 0.8% and 1.5%, largest 6.4%
            assert np.median(rel) < 0.05 and rel.max() < 0.15, (np.median(rel), rel.max())
        assert any("variances recovered from the test ratios" in n for n in log.notes)


def test_the_libraries_open_the_files_and_count_what_was_written(export):
    r, _, logs = export
    s = r["sensors"]
    n = {k: len(s[f"{k}_t"]) for k in ("imu", "gps", "mag", "baro", "vio")}
    reader = DFReader.DFReader_binary(str(logs / "flight_0001.bin"))
    counts = collections.Counter()
    while (m := reader.recv_msg()) is not None:
        counts[m.get_type()] += 1
        if m.get_type() == "EV":
            assert m.Id in (10, 28)                   # armed, not landed: the flight is under way
    assert counts["IMU"] == n["imu"] and counts["MAG"] == n["mag"] and counts["BARO"] == n["baro"]
    assert counts["GPS"] == counts["GPA"] == counts["ATT"] == counts["XKF1"] == counts["XKF3"] == counts["SIM"] == n["gps"]
    assert counts["VISP"] == counts["VISV"] == n["vio"] and counts["ARM"] == 1 and counts["EV"] == 2
    assert reader.clock.timebase > 1.7e9            # GPS week and time: pymavlink puts the flight in 2024
    u = ULog(str(logs / "flight_0001.ulg"))
    topics = {d.name: len(d.data["timestamp"]) for d in u.data_list}
    assert topics["sensor_combined"] == n["imu"] and topics["vehicle_magnetometer"] == n["mag"]
    assert topics["vehicle_air_data"] == n["baro"] and topics["vehicle_visual_odometry"] == n["vio"]
    for name in ("vehicle_gps_position", "vehicle_attitude", "vehicle_local_position", "estimator_innovations",
                 "estimator_innovation_variances", "estimator_innovation_test_ratios",
                 "vehicle_local_position_groundtruth", "vehicle_attitude_groundtruth"):
        assert topics[name] == n["gps"], name
    assert (u.get_dataset("vehicle_status").data["arming_state"] == 2).all()
    assert not u.get_dataset("vehicle_land_detected").data["landed"].any()
    assert "quadformer" in u.msg_info_dict["sys_name"] and "simulat" in u.logged_messages[0].message
    log = read_log(logs / "flight_0001.bin")
    assert "firmware" not in log.vehicle and any("quadformer simulator" in m for m in log.vehicle["messages"])
    assert any("ARM events: armed 0.00 s" in n for n in log.notes)


def test_an_attacked_flight_has_its_attack_beside_its_logs(export):
    r, ds, logs = export
    a = r["attacks"]
    assert a.attacked.tolist() == [True, False]
    assert sorted(p.name for p in logs.iterdir()) == ["flight_0000.attack.json", "flight_0000.bin", "flight_0000.ulg",
                                                      "flight_0001.bin", "flight_0001.ulg"]
    note = json.loads((logs / "flight_0000.attack.json").read_text())
    assert note["attack_type"] == "bias" and note["onset_s"] == a.onset[0] and note["end_s"] == a.end[0]
    assert note["magnitude_m"] == a.magnitude[0] and note["onset_boot_s"] == BOOT_T0 + a.onset[0]
    # the log's GPS is the spoofed fix: the dataset's received GPS, offset from the honest one in the window
    f = ds.flights[ds.flights.flight_id == 0]
    log = read_log(logs / "flight_0000.ulg")
    np.testing.assert_allclose(log.gps[["x", "y", "z"]].to_numpy(), f[["gps_pos_x", "gps_pos_y", "gps_pos_z"]],
                               atol=1e-6)
    lab = f.label.to_numpy() == 1
    t_log = log.gps.t.to_numpy() + log.boot_t0 - BOOT_T0
    assert lab.any() and t_log[lab][0] == pytest.approx(note["onset_s"], abs=0.1)
    d = np.linalg.norm(f[["atk_d_x", "atk_d_y", "atk_d_z"]].to_numpy()[lab], axis=1)
    np.testing.assert_allclose(d, note["magnitude_m"])


@pytest.mark.parametrize("fmt", ["dataflash", "ulog"])
def test_detect_scores_the_exported_logs_from_both_residue_sources(fmt, export, tmp_path):
    """A chi2 gate fit on the clean flight's residues (NIS) of each source: the replayed filter's,
    and the autopilot's own (the DataFlash log's NIS over the variances recovered from EKF3's test
    ratios). Both sources score the spoofed flight's log."""
    _, _, logs = export
    clean, spoofed = logs / f"flight_0001{SUFFIX[fmt]}", logs / f"flight_0000{SUFFIX[fmt]}"
    for residues in ("ekf", "autopilot"):
        flights, _ = log_rows(read_log(clean), residues)
        rows = pd.concat([f.rows for f in flights], ignore_index=True)
        det = make("chi2")
        det.fit(rows)
        scores = det.decision_function(rows)
        det.calibrate(float(np.quantile(scores, 0.99)), float(np.max(scores)))
        model = det.save(tmp_path / f"{residues}.json")
        out = tmp_path / f"det-{residues}"
        res = runner.invoke(app, ["detect", str(spoofed), "--model", str(model), "--residues", residues,
                                  "--out", str(out), "--quiet"])
        assert res.exit_code == 0, res.output
        summary = json.loads((out / spoofed.name / "summary.json").read_text())
        assert summary["residues"] == residues
        scored = pd.read_csv(out / spoofed.name / "scores.csv")
        assert len(scored) > 30 and np.isfinite(scored.score).all()
        assert scored.score.max() > det.threshold_           # the 4-6 m spoof from 2-3 s on is seen


def test_simulate_export_writes_the_logs_beside_the_same_dataset(tmp_path):
    base = ["simulate", "--flights", "2", "--duration", "1", "--attack", "bias", "--onset", "0.3,0.5",
            "--sensors", "gps+imu+mag+baro", "--quiet"]
    res = runner.invoke(app, [*base, "--out", str(tmp_path / "with"), "--export", "ulog", "--export", "dataflash"])
    assert res.exit_code == 0, res.output
    logs = tmp_path / "with" / "logs"
    assert f"flight logs in {logs}: 2 .ulg, 2 .bin, 1 attack notes" in res.output
    assert {p.name for p in logs.iterdir()} == {"flight_0000.ulg", "flight_0000.bin", "flight_0001.ulg",
                                                "flight_0001.bin", "flight_0000.attack.json"}
    assert not list(tmp_path.glob(".*"))                                   # no staging leftovers
    res = runner.invoke(app, [*base, "--out", str(tmp_path / "without")])
    assert res.exit_code == 0, res.output
    a, b = load_dataset(tmp_path / "with"), load_dataset(tmp_path / "without")
    pd.testing.assert_frame_equal(a.flights, b.flights)                     # recording the logs changes nothing
    assert read_log(logs / "flight_0001.bin").mag is not None and read_log(logs / "flight_0001.ulg").odometry is None
    res = runner.invoke(app, [*base, "--out", str(tmp_path / "bad"), "--export", "ulog,csv"])
    assert res.exit_code == 2 and "unknown log format 'csv'" in res.output and "ulog, dataflash" in res.output
    assert not (tmp_path / "bad").exists()
    assert export_formats(["dataflash", "ulog,dataflash"]) == ("ulog", "dataflash")


def test_an_exported_capture_carries_the_receivers_signature(tmp_path):
    """A captured flight exported both ways: read back, its receiver stream shows the satellites
    dropping and recovering, eph and speed accuracy inflating for seconds, the noise rising (PX4's
    noise_per_ms; ArduPilot's GPS messages have no noise field) and the reports of the lost lock
    (fix type 1, no fix in the gps stream); ``detect`` labels the alert at the capture degraded."""
    out = tmp_path / "cap"
    res = runner.invoke(app, ["simulate", "--flights", "1", "--duration", "16", "--attack", "capture", "--onset",
                              "3,3", "--attack-fraction", "1", "--sensors", "gps+imu+mag+baro", "--seed", "2",
                              "--set", "attack.lock_loss_s=[0.25, 0.25]", "--export", "ulog,dataflash",
                              "--out", str(out), "--quiet"])
    assert res.exit_code == 0, res.output
    note = json.loads((out / "logs" / "flight_0000.attack.json").read_text())
    assert note["attack_type"] == "capture" and note["lock_loss_s"] == 0.25 and 5.0 <= note["magnitude_m"] <= 15.0
    onset = BOOT_T0 + note["onset_s"]
    for suffix in (".ulg", ".bin"):
        log = read_log(out / "logs" / f"flight_0000{suffix}")
        rec = log.receiver.assign(t=log.receiver.t + log.boot_t0)          # the vehicle's clock
        before, during = rec[rec.t < onset], rec[(rec.t >= onset) & (rec.t < onset + 4.0)]
        after = rec[rec.t >= onset + 2.0 + note["recover_s"] + 0.1]
        assert (before.satellites == 12).all() and (after.satellites == 12).all()
        assert during.satellites.min() == round(12 * note["satellites_share"]) <= 6
        assert during.eph.max() > 3.0 * before.eph.max() and (after.eph - before.eph.iloc[0]).abs().max() < 0.01
        assert during.speed_acc.max() > 8.0 * before.speed_acc.max()
        lost = rec[rec.fix_type < 2]
        assert len(lost) == 3 and lost.t.min() == pytest.approx(onset, abs=0.1) and lost.t.max() < onset + 0.25
        assert (rec.fix_type[rec.fix_type >= 2] == 3).all() and len(log.gps) == len(rec) - 3
        assert not np.isin(np.round(log.gps.t + log.boot_t0, 3), np.round(lost.t, 3)).any()
        if suffix == ".ulg":
            assert (before.noise == 100).all() and during.noise.max() == round(100 * (1 + note["noise_rise"]))
        else:
            assert rec.noise.isna().all()
    # detect: an alert at the capture is typed degraded (the receiver says its fix is lost or worse)
    log = out / "logs" / "flight_0000.ulg"
    flights, _ = log_rows(read_log(log), "ekf")
    rows = pd.concat([f.rows for f in flights], ignore_index=True)
    det = make("chi2").fit(rows[rows.t + read_log(log).boot_t0 < onset - 0.5])
    det.calibrate(1e9, 1e9)                                               # only the receiver raises alerts
    model = det.save(tmp_path / "chi2.json")
    res = runner.invoke(app, ["detect", str(log), "--model", str(model), "--out", str(tmp_path / "det"), "--quiet"])
    assert res.exit_code == 0, res.output
    alerts = pd.read_csv(tmp_path / "det" / log.name / "alerts.csv")
    deg = alerts[alerts.kind == "degraded"]
    assert len(deg) and (deg.start_s.min() + read_log(log).boot_t0) == pytest.approx(onset, abs=0.2)
