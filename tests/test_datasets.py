"""Part 6: datasets, reproducibility, atomic writes, bad input; part 1: the CLI."""

import json

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from quadformer.cli import app
from quadformer.config import AttackConfig, ConfigError, SimConfig
from quadformer.dataset import DatasetError, load_dataset, write_dataset
from quadformer.simulation import simulate
from quadformer.simulation.closed_loop import simulate_batch

SMALL = SimConfig(model="II", noise="exponential", flights=3, duration=3.0, seed=5,
                  attack=AttackConfig(kind="ramp", onset=(1.0, 2.0), fraction=1.0))


def test_columns_and_labels(bias_dataset):
    f = bias_dataset.flights
    for c in ["flight_id", "t", "label", "attack_type", "true_pos_x", "true_pos_y", "true_pos_z",
              "ref_pos_x", "ref_pos_y", "ref_pos_z", "gps_pos_x", "gps_pos_y", "gps_pos_z",
              "est_pos_x", "est_pos_y", "est_pos_z", "res_gps_nis"]:
        assert c in f.columns
    assert len(bias_dataset.residue_columns) >= 20
    assert len(f) == 6 * 240 and f.groupby("flight_id").size().eq(240).all()
    s = bias_dataset.scenarios
    assert s.attacked.sum() == 3
    for _, row in s.iterrows():
        g = f[f.flight_id == row.flight_id]
        lab = g.label.to_numpy() == 1
        if row.attacked:
            assert np.array_equal(lab, ((g.t >= row.onset) & (g.t < row.end)).to_numpy())
            assert set(g.attack_type[lab]) == {"bias"}
        else:
            assert not lab.any()
    assert not f[bias_dataset.residue_columns].isna().any().any()


def test_same_seed_same_data_whatever_the_batch():
    a = simulate(SMALL.replace(batch_size=3))
    b = simulate(SMALL.replace(batch_size=1))
    pd.testing.assert_frame_equal(a.flights, b.flights, check_exact=True)
    pd.testing.assert_frame_equal(a.scenarios, b.scenarios, check_exact=True)
    # a flight simulated alone equals the same flight inside a batch
    alone = simulate_batch(SMALL, np.array([2]), np.array([True]))
    assert np.array_equal(alone["res_gps_r"][0], a.flights[a.flights.flight_id == 2]
                          .filter(like="res_gps_r_").to_numpy())
    c = simulate(SMALL.replace(seed=6))
    assert not np.array_equal(a.flights.res_gps_nis, c.flights.res_gps_nis)


def test_write_is_atomic_and_round_trips(tmp_path, bias_dataset, monkeypatch):
    out = tmp_path / "ds"
    write_dataset(bias_dataset, out)
    back = load_dataset(out)
    pd.testing.assert_frame_equal(back.flights, bias_dataset.flights)
    assert json.loads((out / "meta.json").read_text())["config"]["model"] == "II"
    assert back.config == bias_dataset.config
    with pytest.raises(FileExistsError):
        write_dataset(bias_dataset, out)

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(pd.DataFrame, "to_parquet", boom)
    with pytest.raises(OSError):
        write_dataset(bias_dataset, tmp_path / "ds2")
    with pytest.raises(OSError):
        write_dataset(bias_dataset, out, overwrite=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]   # no half-written directory
    monkeypatch.undo()
    assert len(load_dataset(out).flights) == len(bias_dataset.flights)  # the old one is intact


def test_corrupt_or_missing_files_are_named(tmp_path, bias_dataset):
    out = write_dataset(bias_dataset, tmp_path / "ds")
    data = (out / "flights.parquet").read_bytes()
    (out / "flights.parquet").write_bytes(data[: len(data) // 2])
    with pytest.raises(DatasetError, match="cannot read parquet"):
        load_dataset(out)
    (out / "meta.json").write_text("{")
    with pytest.raises(DatasetError, match="meta.json"):
        load_dataset(out)
    with pytest.raises(DatasetError, match="no such dataset"):
        load_dataset(tmp_path / "nope")


@pytest.mark.parametrize("kwargs, field", [
    ({"model": "III"}, "model"),
    ({"noise": "cauchy"}, "noise"),
    ({"flights": 0}, "flights"),
    ({"duration": -5.0}, "duration"),
    ({"duration": 30.0, "attack": AttackConfig(kind="bias")}, "attack.onset"),
])
def test_bad_config_names_the_field(kwargs, field):
    with pytest.raises(ConfigError, match=f"^{field}"):
        SimConfig(**kwargs)


def test_unknown_config_key_is_rejected():
    with pytest.raises(ConfigError, match="gps.pos_noise: unknown setting"):
        SimConfig.from_dict({"gps": {"pos_noise": 1.0}})


def test_cli_simulate_end_to_end(tmp_path):
    runner = CliRunner()
    cfg_file = tmp_path / "c.toml"
    cfg_file.write_text('model = "II"\n[attack]\nkind = "bias"\nmagnitude = [2.0, 2.5]\n')
    out = tmp_path / "cli"
    res = runner.invoke(app, ["simulate", "--config", str(cfg_file), "--flights", "2", "--duration", "6",
                              "--onset", "3,5", "--set", "gps.gm_std=0.2", "--out", str(out), "--quiet"])
    assert res.exit_code == 0, res.output
    ds = load_dataset(out)
    cfg = ds.config
    assert (cfg.model, cfg.attack.kind, cfg.attack.magnitude, cfg.attack.onset, cfg.gps.gm_std) == \
        ("II", "bias", (2.0, 2.5), (3.0, 5.0), 0.2)
    assert ds.scenarios.attacked.sum() == 1
    assert ds.meta["versions"]["rotorpy"] == "3.0.0"


@pytest.mark.parametrize("args, message", [
    (["--model", "X"], "model: unknown model 'X'"),
    (["--attack", "jam"], "attack.kind: unknown attack 'jam'"),
    (["--flights", "0"], "flights: must be an integer >= 1"),
    (["--duration", "-1"], "duration: must be a positive"),
    (["--attack", "bias", "--duration", "20"], "attack.onset: the latest onset"),
])
def test_cli_bad_input(tmp_path, args, message):
    res = CliRunner().invoke(app, ["simulate", "--out", str(tmp_path / "x"), "--quiet", *args])
    assert res.exit_code == 2
    assert message in res.output
    assert not (tmp_path / "x").exists()
