"""Sensor configurations: the default (gps+imu+vio) data is unchanged, bit for bit."""

from pathlib import Path

import numpy as np
import pytest

from quadformer.config import AttackConfig, SimConfig
from quadformer.simulation import simulate

PIN = Path(__file__).parent / "fixtures" / "pins" / "default_sensors.npz"
# the configuration tests/fixtures/pins/make_default_sensors.py recorded
PIN_CFG = SimConfig(model="II", noise="laplace", flights=2, duration=6.0, seed=21,
                    attack=AttackConfig(kind="bias", onset=(1.0, 3.0), duration=(1.0, 2.0), fraction=1.0))


def test_default_configuration_reproduces_the_recorded_dataset():
    """Recorded before magnetometer and barometer existed: every column, same names, same order,
    same values bit for bit. (A tolerance would not do: one ulp on one filter noise std moves
    this dataset by under 1e-13.) The recording holds this platform's floating-point results;
    tests/fixtures/pins/make_default_sensors.py says how it was made."""
    pin = np.load(PIN)
    f = simulate(PIN_CFG).flights
    assert list(f.columns) == [*pin["columns"][:3], "attack_type", *pin["columns"][3:]]
    got = f.drop(columns=["attack_type"]).to_numpy(dtype=np.float64)
    diff = np.abs(got - pin["values"])
    assert np.array_equal(got, pin["values"]), \
        f"{int((diff > 0).sum())} values differ, most in {f.columns.drop('attack_type')[diff.max(0).argmax()]} " \
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
