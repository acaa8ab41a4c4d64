"""Simulated flights logged as real logs are: IMU rate and kind, airframe vibration, GPS rate,
latency and read jitter (``logs.conditions``), written by the exporter and read back.

One 6 s flight (seed 3, the GPS's own error made negligible so that a fix's lag behind the truth
shows), exported under several conditions; each log is read back with ``read_log`` and, for the
fields the readers may re-derive (the receiver's time of week), opened with pymavlink and pyulog.
Tolerances: the vibration's spread to 12 % (250 samples), the rates to 1e-6 relative, the
stamps as written to the formats' microsecond and as read back to 5 ms (a reader may stamp the
fixes at the receiver's epochs again, through a fitted line), the lag of a fix behind the truth
to 10 ms.
"""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest
from pymavlink import DFReader
from pyulog import ULog
from typer.testing import CliRunner

from quadformer.cli import app
from quadformer.config import GPSConfig, SimConfig
from quadformer.experiments.flight_logs import BOOT_T0, CONDITIONS_FILE, UTC0, LogExport, check_conditions
from quadformer.logs import read_log
from quadformer.logs.conditions import LogConditions
from quadformer.logs.writing import gps_week_ms
from quadformer.simulation import simulate

runner = CliRunner()
SUFFIX = {"ulog": ".ulg", "dataflash": ".bin"}
CFG = SimConfig(flights=1, duration=6.0, seed=3, sensors="gps+imu+mag+baro",
                gps=GPSConfig(pos_std_h=0.01, pos_std_v=0.01, vel_std=0.01, gm_std=0.0))
IMU = ["ax", "ay", "az", "gx", "gy", "gz"]
VIB = (2.0, 0.05)                  # m/s^2, rad/s: RMS per axis
LATENCY, JITTER = 0.12, 0.05       # s


@pytest.fixture(scope="module")
def batch():
    out = []
    simulate(CFG, on_batch=out.append)
    return out[0]


def _write(batch, directory, conditions=None, cfg=CFG):
    LogExport(cfg, directory, ("ulog", "dataflash"), conditions=conditions)(batch)
    return directory


def _read(directory, fmt):
    return read_log(directory / f"flight_0000{SUFFIX[fmt]}")


def _digests(directory):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(directory.iterdir())}


def test_no_conditions_write_the_logs_of_before_byte_for_byte(batch, tmp_path):
    assert not LogConditions().active and LogConditions(imu_hz=50).active
    plain = tmp_path / "plain"
    LogExport(CFG, plain, ("ulog", "dataflash"))(batch)
    same = _write(batch, tmp_path / "default", LogConditions())
    assert _digests(plain) == _digests(same) and not (same / CONDITIONS_FILE).exists()


@pytest.mark.parametrize("fmt", ["dataflash", "ulog"])
def test_the_imu_at_the_rate_asked_samples_alias_the_vibration_and_deltas_average_it(batch, tmp_path, fmt):
    imu = {}
    for kind in ("samples", "integrated"):
        for vib in (False, True):
            c = LogConditions(imu_hz=50, imu=kind, vibration_accel=VIB[0] * vib, vibration_gyro=VIB[1] * vib)
            log = _read(_write(batch, tmp_path / f"{kind}{vib}", c), fmt)
            t = log.imu["t"].to_numpy()
            assert 1.0 / np.median(np.diff(t)) == pytest.approx(50.0, rel=1e-6) and len(t) == 300
            imu[kind, vib] = log.imu[IMU].to_numpy()
    sim = np.asarray(batch["sensors"]["imu"][0], dtype=float)          # 100 Hz, FLU: ax..az, gx..gz
    np.testing.assert_allclose(imu["samples", False], sim[1::2], atol=1e-4)
    np.testing.assert_allclose(imu["integrated", False], sim.reshape(300, 2, 6).mean(axis=1), atol=1e-4)
    stated = np.repeat(VIB, 3)
    sampled = imu["samples", True] - imu["samples", False]               # the vibration, aliased below 25 Hz
    np.testing.assert_allclose(sampled.std(axis=0), stated, rtol=0.12)
    # the accelerometers' spread above the clean one (the gyros' manoeuvres, 5 times their vibration,
    # leave the difference of variances to chance)
    above = np.sqrt(imu["samples", True].var(axis=0) - imu["samples", False].var(axis=0))[:3]
    np.testing.assert_allclose(above, VIB[0], rtol=0.25)
    averaged = imu["integrated", True] - imu["integrated", False]
    assert (averaged.std(axis=0) < 0.25 * stated).all()                  # mostly averaged out over 20 ms
    clean, shaken = imu["integrated", False].std(axis=0), imu["integrated", True].std(axis=0)
    assert (np.abs(shaken - clean) < 0.25 * stated).all()


def _raw_gps(path, fmt):
    """(stamps, receiver's times) of each GPS message: the flight's time of its stamp (s) and the
    GPS week and ms of week (DataFlash) or UTC microseconds (ULog) the receiver wrote."""
    if fmt == "dataflash":
        rows = []
        reader = DFReader.DFReader_binary(str(path))
        while (m := reader.recv_match(type="GPS")) is not None:
            rows.append((m.TimeUS, m.GWk, m.GMS))
        us, week, ms = np.array(rows).T
        return us / 1e6 - BOOT_T0, (week, ms)
    d = ULog(str(path), ["vehicle_gps_position"]).get_dataset("vehicle_gps_position").data
    return d["timestamp"] / 1e6 - BOOT_T0, d["time_utc_usec"]


@pytest.mark.parametrize("fmt", ["dataflash", "ulog"])
def test_gps_at_the_rate_asked_lags_by_its_latency_and_jitters_within_the_bound(batch, tmp_path, fmt):
    c = LogConditions(gps_hz=5, gps_latency_s=LATENCY, gps_jitter_s=JITTER)
    directory = _write(batch, tmp_path / "gps", c)
    epochs = np.asarray(batch["sensors"]["gps_t"])[1::2]               # every second 10 Hz fix: 0.2, 0.4, ...
    stamps, receiver = _raw_gps(directory / f"flight_0000{SUFFIX[fmt]}", fmt)
    if fmt == "dataflash":                                             # the receiver's time stays the epoch's
        week, ms = gps_week_ms(UTC0 + epochs)
        assert (receiver[0] == week).all() and (receiver[1] == ms).all()
    else:
        assert (receiver == np.round((UTC0 + epochs) * 1e6)).all()
    delay = stamps - epochs
    assert delay.min() >= LATENCY - 1e-6 and delay.max() <= LATENCY + JITTER + 1e-6
    assert delay.std() == pytest.approx(JITTER / np.sqrt(12), rel=0.4)   # uniform jitter, 30 draws
    log = _read(directory, fmt)
    t = log.gps["t"].to_numpy() + log.boot_t0 - BOOT_T0                # the flight's clock
    assert len(t) == len(epochs) and np.median(np.diff(t)) == pytest.approx(0.2, abs=0.02)
    assert (t - epochs >= LATENCY - 5e-3).all() and (t - epochs <= LATENCY + JITTER + 5e-3).all()
    truth = log.truth
    tt = truth["t"].to_numpy() + log.boot_t0 - BOOT_T0
    p_true = np.column_stack([np.interp(t, tt, truth[a]) for a in "xyz"])
    v_true = np.column_stack([np.interp(t, tt, truth[a]) for a in ("vx", "vy", "vz")])
    speed2 = (v_true ** 2).sum(axis=1)
    assert (speed2 > 4.0).all()                                        # the vehicle moves at over 2 m/s
    lag = ((p_true - log.gps[["x", "y", "z"]].to_numpy()) * v_true).sum(axis=1) / speed2
    assert LATENCY - 0.01 <= np.median(lag) <= LATENCY + JITTER + 0.01   # fix = truth (latency + read) ago
    assert log.vehicle["gps_delay_s"] == pytest.approx(LATENCY)


def test_an_unstated_latency_leaves_the_delay_parameters_at_zero(batch, tmp_path):
    directory = _write(batch, tmp_path / "unstated", LogConditions(gps_latency_s=LATENCY, state_latency=False))
    assert "gps_delay_s" not in _read(directory, "dataflash").vehicle        # GPS_DELAY_MS 0: the driver's own
    assert _read(directory, "ulog").vehicle["gps_delay_s"] == 0.0
    written = json.loads((directory / CONDITIONS_FILE).read_text())
    assert written["gps_latency_s"] == LATENCY and written["state_latency"] is False and written["seed"] == CFG.seed


def test_the_same_seed_writes_the_same_bytes(batch, tmp_path):
    c = LogConditions(imu_hz=25, vibration_accel=1.0, vibration_gyro=0.02, gps_hz=5, gps_jitter_s=0.03)
    a, b = _write(batch, tmp_path / "a", c), _write(batch, tmp_path / "b", c)
    other = _write(batch, tmp_path / "other", c, cfg=CFG.replace(seed=4))
    assert _digests(a) == _digests(b)
    assert _digests(a)["flight_0000.bin"] != _digests(other)["flight_0000.bin"]


@pytest.mark.parametrize("values, message", [
    ({"imu_hz": -50}, "imu_hz must be from 25 to 400 Hz"),
    ({"imu_hz": 500}, "imu_hz must be from 25 to 400 Hz"),
    ({"gps_hz": 20}, "gps_hz must be from 1 to 10 Hz"),
    ({"gps_hz": 0.5}, "gps_hz must be from 1 to 10 Hz"),
    ({"imu": "filtered"}, "imu must be one of samples, integrated"),
    ({"vibration_accel": -1.0}, "vibration_accel must be a non-negative number of m/s"),
    ({"vibration_gyro": float("nan")}, "vibration_gyro must be"),
    ({"gps_latency_s": -0.1}, "gps_latency_s must be from 0 to 0.5 s"),
    ({"gps_jitter_s": -0.01}, "gps_jitter_s must be a non-negative"),
    ({"gps_hz": 5, "gps_jitter_s": 0.2}, "shorter than the logged GPS interval"),
])
def test_impossible_conditions_are_refused_naming_the_value(values, message):
    with pytest.raises(ValueError, match=message):
        LogConditions(**values)


@pytest.mark.parametrize("values, message", [
    ({"imu_hz": 200}, "imu_hz 200 Hz is faster than the simulated IMU \\(100 Hz\\)"),
    ({"imu_hz": 40}, "imu_hz 40 Hz does not divide the simulated IMU rate"),
    ({"gps_hz": 4}, "gps_hz 4 Hz does not divide the simulated GPS rate"),
    ({"gps_jitter_s": 0.1}, "shorter than the logged GPS interval \\(0.1 s\\)"),
])
def test_conditions_the_simulation_cannot_give_are_refused(values, message):
    with pytest.raises(ValueError, match=message):
        check_conditions(CFG, LogConditions(**values))
    assert check_conditions(CFG.replace(dt=0.0025), LogConditions(imu_hz=400)) == (1, 1)
    assert check_conditions(CFG, LogConditions(imu_hz=33.33, gps_hz=2.5)) == (3, 4)


def test_the_command_line_logs_under_the_conditions_asked(tmp_path):
    out = tmp_path / "sim"
    res = runner.invoke(app, ["simulate", "--out", str(out), "--flights", "1", "--duration", "2", "--quiet",
                              "--export", "dataflash", "--log-imu-hz", "50", "--log-imu", "integrated",
                              "--log-vibration", "1.5", "--log-gps-hz", "5", "--log-gps-latency-ms", "100",
                              "--log-gps-jitter-ms", "20"])
    assert res.exit_code == 0, res.output
    log = read_log(out / "logs" / "flight_0000.bin")
    assert 1.0 / np.median(np.diff(log.imu["t"])) == pytest.approx(50.0, rel=1e-6)
    assert len(log.gps) == 10 and log.vehicle["gps_delay_s"] == pytest.approx(0.1)
    written = json.loads((out / "logs" / CONDITIONS_FILE).read_text())
    assert written["imu"] == "integrated" and written["gps_jitter_s"] == pytest.approx(0.02)
    for args, message in ((["--export", "dataflash", "--log-imu-hz", "200"], "--log-imu-hz"),
                          (["--export", "ulog", "--log-gps-hz", "12"], "--log-gps-hz"),
                          (["--log-gps-hz", "5"], "add --export")):
        res = runner.invoke(app, ["simulate", "--out", str(tmp_path / "refused"), "--flights", "1", *args])
        assert res.exit_code == 2 and message in res.output and not (tmp_path / "refused").exists()
