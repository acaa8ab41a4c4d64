"""Sensor configurations: the default (gps+imu+vio) data is unchanged; settings
are validated; the columns and the command line follow the configuration."""

import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from quadformer.cli import app
from quadformer.config import AttackConfig, BaroConfig, ConfigError, EKFConfig, MagConfig, SimConfig
from quadformer.dataset import load_dataset
from quadformer.detectors.windows import input_features
from quadformer.estimator.eskf import noise_model
from quadformer.estimator.schema import DETECTOR_FEATURES, PERSISTENT, columns, groups_for
from quadformer.experiments.cache import dataset_key
from quadformer.simulation import simulate

PIN = Path(__file__).parent / "fixtures" / "pins" / "default_sensors.npz"
# the configuration tests/fixtures/pins/make_default_sensors.py recorded
PIN_CFG = SimConfig(model="II", noise="laplace", flights=2, duration=6.0, seed=21,
                    attack=AttackConfig(kind="bias", onset=(1.0, 3.0), duration=(1.0, 2.0), fraction=1.0))


def test_default_configuration_reproduces_the_recorded_dataset():
    """Recorded before magnetometer and barometer existed: every column, same names, same order,
    the persistent residues (added later) appended after them, and the same values to 1e-9
    relative (and absolute). The recording holds one platform's floating-point results: another
    CPU's vector maths moves them by about 1e-14, which the tolerance admits; a shifted random
    draw or a changed model moves them by the noise, 1e-3 and more. (Below the tolerance: a
    change of one ulp in one filter constant, which moves this dataset by under 1e-13.)
    tests/fixtures/pins/make_default_sensors.py says how it was made."""
    pin = np.load(PIN)
    f = simulate(PIN_CFG).flights
    new = columns(*PERSISTENT, "res_ref_reset")     # added later, after every pinned column
    assert list(f.columns) == [*pin["columns"][:3], "attack_type", *pin["columns"][3:], *new]
    f = f.drop(columns=new)
    got = f.drop(columns=["attack_type"]).to_numpy(dtype=np.float64)
    diff = np.abs(got - pin["values"])
    bad = diff > 1e-9 * (1 + np.abs(pin["values"]))
    assert not bad.any(), \
        f"{int(bad.sum())} values differ, most in {f.columns.drop('attack_type')[diff.max(0).argmax()]} " \
        f"(max {diff.max():.3g})"
    assert np.array_equal(f["attack_type"].to_numpy(dtype=str), pin["attack_type"])
    # a few values written out, to 1e-12
    row = {c: i for i, c in enumerate(f.columns)}
    for col, values in {
        "res_gps_nis": (0.412277522534959, 3.225491038450171, 3.2634073577529157),
        "res_gps_r_px": (0.04459097772476733, -0.324555853360043, -0.14160583158998885),
        "res_vio_r_thz": (0.004946720875332352, 0.0031834771631378232, -0.0052409915949578854),
        "res_vio_nis_mean": (2.990741635389742, 13.63770692017442, 3.769629610527545),
        "est_pos_z": (13.714882325760064, 13.755292676658858, 21.25022140178187),
    }.items():
        assert f.iloc[[9, 59, 119], row[col]].to_numpy() == pytest.approx(values, rel=1e-12, abs=1e-12), col


@pytest.mark.parametrize("text, canonical", [
    ("gps+imu+vio", "gps+imu+vio"),
    ("imu+gps+mag+baro", "gps+imu+mag+baro"),
    (" BARO + mag+vio+imu+gps ", "gps+imu+vio+mag+baro"),
])
def test_sensor_configuration_is_stored_in_canonical_form(text, canonical):
    cfg = SimConfig(sensors=text)
    assert cfg.sensors == canonical
    assert SimConfig.from_dict(cfg.to_dict()) == cfg


@pytest.mark.parametrize("kwargs, message", [
    ({"sensors": "gps+imu+lidar"}, "sensors: unknown sensor 'lidar' in 'gps+imu+lidar'; choose from gps+imu+vio, "
                                   "gps+imu+mag+baro, gps+imu+vio+mag+baro"),
    ({"sensors": "gps+imu"}, "sensors: unsupported sensor configuration 'gps+imu'; choose from"),
    ({"sensors": "imu+vio+mag+baro"}, "sensors: unsupported sensor configuration"),
    ({"sensors": "gps+imu+vio+vio"}, "sensors: a sensor is named twice"),
    ({"sensors": None}, "sensors: must be a string"),
    ({"mag": MagConfig(rate_hz=30.0)}, "mag.rate_hz: the sensor period must be a whole number of simulation steps"),
    ({"baro": BaroConfig(rate_hz=40.0)}, "baro.rate_hz: the sensor period must be a whole number"),
])
def test_bad_sensor_configuration_names_the_field(kwargs, message):
    with pytest.raises(ConfigError, match=f"^{re.escape(message)}"):
        SimConfig(**kwargs)


@pytest.mark.parametrize("make, message", [
    (lambda: MagConfig(noise_std=0.0), "mag.noise_std: must be a positive"),
    (lambda: MagConfig(bias_std=-0.01), "mag.bias_std: must be a non-negative"),
    (lambda: MagConfig(field_h=0.0), "mag.field_h: must be a positive"),
    (lambda: MagConfig(declination_deg=200.0), "mag.declination_deg: must be in [-180, 180]"),
    (lambda: BaroConfig(noise_std=float("nan")), "baro.noise_std: must be a positive"),
    (lambda: BaroConfig(gm_tau=0.0), "baro.gm_tau: must be a positive"),
    (lambda: EKFConfig(mag_heading_std_deg=0.0), "ekf.mag_heading_std_deg: must be a positive"),
    (lambda: SimConfig.from_dict({"mag": {"noise": 1.0}}), "mag.noise: unknown setting"),
])
def test_bad_magnetometer_and_barometer_settings_name_the_field(make, message):
    with pytest.raises(ConfigError, match=f"^{re.escape(message)}"):
        make()


def test_filter_noise_follows_the_sensors_unless_overridden():
    cfg = SimConfig.from_dict({"mag": {"noise_std": 0.003, "bias_std": 0.004, "field_h": 0.2},
                               "baro": {"noise_std": 0.3, "gm_std": 0.4}})
    nm = noise_model(cfg.imu, cfg.gps, cfg.vio, cfg.ekf, 100.0, cfg.mag, cfg.baro)
    assert nm.mag_std.item() == pytest.approx(0.005 / 0.2)        # rad: hypot(noise, bias) / field_h
    assert nm.baro_std.item() == pytest.approx(0.5)
    assert nm.mag_field.tolist() == pytest.approx([0.0, 0.2, -0.42])
    over = cfg.replace(ekf=EKFConfig(mag_heading_std_deg=2.0, baro_std=1.5))
    nm = noise_model(over.imu, over.gps, over.vio, over.ekf, 100.0, over.mag, over.baro)
    assert nm.mag_std.item() == pytest.approx(np.deg2rad(2.0)) and nm.baro_std.item() == 1.5


def test_dataset_cache_keys_of_default_sensors_are_unchanged():
    """Sensor configurations left the default configuration's key as it was (8b1987e9d405c730 at
    format version 2); the persistent residues changed the format (version 3: a cached dataset
    without their columns is simulated again). Settings of a sensor the configuration leaves
    out do not change the key (they do not change the data)."""
    assert dataset_key(SimConfig()) == "14d6a294b3aeaf59"
    assert dataset_key(SimConfig(mag=MagConfig(noise_std=0.1), ekf=EKFConfig(baro_std=2.0))) == "14d6a294b3aeaf59"
    mb = SimConfig(sensors="gps+imu+mag+baro")
    assert dataset_key(mb) != dataset_key(mb.replace(mag=MagConfig(noise_std=0.1)))


def test_detector_inputs_follow_the_columns_present():
    """The default configuration's inputs and their order are unchanged; the magnetometer and
    barometer residues come after the others and the persistent residues last, VIO's are
    simply absent without VIO."""
    default = input_features(pd.DataFrame(columns=columns(*(g.name for g in groups_for("gps+imu+vio")))))
    assert default == [c for c in DETECTOR_FEATURES if not c.startswith(("res_mag", "res_baro"))]
    new = columns(*PERSISTENT)
    assert default[-len(new) - 1:] == ["res_vio_nis_mean", *new]
    nocam = input_features(pd.DataFrame(columns=columns(*(g.name for g in groups_for("gps+imu+mag+baro")))))
    assert nocam[-len(new) - 4:] == ["res_mag_r_yaw", "res_mag_nis", "res_baro_r_z", "res_baro_nis", *new]
    assert not any("vio" in c for c in nocam)


def test_cli_simulate_without_camera(tmp_path):
    out = tmp_path / "nocam"
    res = CliRunner().invoke(app, ["simulate", "--sensors", "imu+gps+mag+baro", "--flights", "1", "--duration", "3",
                                   "--seed", "4", "--out", str(out), "--quiet"])
    assert res.exit_code == 0, res.output
    ds = load_dataset(out)
    assert ds.config.sensors == "gps+imu+mag+baro"
    cols = list(ds.flights.columns)
    assert [c for c in cols if c.startswith(("res_mag", "res_baro"))] == \
        ["res_mag_r_yaw", "res_mag_nis", "res_baro_r_z", "res_baro_nis"]
    assert not [c for c in cols if "vio" in c]
    expected = columns(*(g.name for g in groups_for("gps+imu+mag+baro")))
    assert cols == ["flight_id", "t", "label", "attack_type"] + expected
    assert not ds.flights.isna().any().any()
    # heading innovations of a few degrees, height innovations of about a metre, after the first second
    late = ds.flights[ds.flights.t > 1.0]
    assert late.res_mag_r_yaw.abs().max() < np.deg2rad(10) and late.res_baro_r_z.abs().max() < 4.0
    bad = CliRunner().invoke(app, ["simulate", "--sensors", "gps+imu+sonar", "--out", str(tmp_path / "x"), "--quiet"])
    assert bad.exit_code == 2 and "sensors: unknown sensor 'sonar'" in bad.output
