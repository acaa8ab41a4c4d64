"""End to end: benchmark, fit and evaluate through the CLI, as a user runs them."""

import json
import shutil

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from quadformer.cli import app
from quadformer.detectors import load
from quadformer.dataset import write_dataset
from quadformer.experiments.cache import dataset_key
from quadformer.experiments.grid import PROFILES, profile_configs

runner = CliRunner()


@pytest.fixture(scope="module")
def dataset_dir(bias_dataset, tmp_path_factory):
    return write_dataset(bias_dataset, tmp_path_factory.mktemp("data") / "ds")


def test_benchmark_writes_schema_tables_report_and_reuses_cache(dataset_dir, tmp_path):
    # Fill the cache with one small real dataset under every demo configuration's key, so
    # the test exercises the harness without simulating eight datasets.
    cache = tmp_path / "cache"
    for name, cfg in profile_configs(PROFILES["demo"]):
        shutil.copytree(dataset_dir, cache / f"{name}-{dataset_key(cfg)}")
    before = {p: p.stat().st_mtime for p in cache.rglob("flights.parquet")}
    out = tmp_path / "bench"
    res = runner.invoke(app, ["benchmark", "--profile", "demo", "--methods", "chi2,cusum", "--cache",
                              str(cache), "--out", str(out), "--quiet"])
    assert res.exit_code == 0, res.output
    assert "Model I" in res.output and "Model II" in res.output and "report.html" in res.output
    assert before == {p: p.stat().st_mtime for p in cache.rglob("flights.parquet")}   # reused, not simulated

    r = json.loads((out / "results.json").read_text())
    assert r["profile"] == "demo" and len(r["configs"]) == 8
    c = r["configs"][0]
    assert {"model", "noise", "attack", "n_test_flights", "methods"} <= set(c)
    keys = {"precision", "recall", "f1", "event_precision", "event_recall", "event_f1", "delay_median_s",
            "delay_p95_s", "false_alarms_per_hour", "auroc", "auprc", "threshold"}
    assert keys <= set(c["methods"]["cusum"])
    for model in ("I", "II"):
        for ext in ("md", "csv", "tex"):
            assert (out / f"table_model_{model}.{ext}").stat().st_size > 0
        csv = pd.read_csv(out / f"table_model_{model}.csv", index_col=0)
        assert list(csv.index) == ["chi2", "cusum"] and csv.shape[1] == 12
    html = (out / "report.html").read_text()
    assert "data:image/png;base64," in html and "point-adjusted" in html and "<table" in html
    assert (out / "figures" / "f1_by_config.png").exists()
    alerts = pd.read_csv(out / "alerts.csv")
    assert {"config", "method", "flight_id", "start_s", "onset_s", "attack_type", "score", "end_s"} <= set(alerts.columns)
    assert set(alerts.method) <= {"chi2", "cusum"} and len(alerts) > 0
    assert len(list((cache / "models").rglob("cusum-*.tuned.json"))) == 8      # tuned detectors cached


def test_resilience_cli_flies_four_policies_and_reuses_tuned_detectors(dataset_dir, tmp_path):
    cache = tmp_path / "cache"
    for name, cfg in profile_configs(PROFILES["demo"]):
        shutil.copytree(dataset_dir, cache / f"{name}-{dataset_key(cfg)}")
    out = tmp_path / "res"
    args = ["--profile", "demo", "--cache", str(cache), "--quiet", "--workers", "2"]
    res = runner.invoke(app, ["benchmark", "--methods", "cusum", "--out", str(tmp_path / "bench"), *args])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["resilience", "--detector", "cusum", "--out", str(out), *args])
    assert res.exit_code == 0, res.output
    assert "naive" in res.output and "oracle" in res.output and "alerts.csv" in res.output
    r = json.loads((out / "results.json").read_text())
    assert r["policies"] == ["naive", "px4", "resilient", "oracle"] and len(r["configs"]) == 8
    c = r["configs"][0]
    assert c["model_from_cache"] is True                 # the benchmark's tuned CUSUM, not a new one
    assert set(c["policies"]) == set(r["policies"])
    for p in r["policies"]:
        assert c["policies"][p]["attacked_flights"] + c["policies"][p]["clean_flights"] == c["test_flights"]
    assert c["policies"]["oracle"]["wrongly_excluded_fraction"] == 0.0
    assert c["policies"]["naive"]["excluded_during_attack"] == 0
    traj = pd.read_parquet(out / "trajectories" / f"{c['name']}.parquet")
    assert len(traj) == 4 * c["test_flights"] * 240
    html = (out / "report.html").read_text()
    assert html.count("data:image/png;base64,") >= 1 and "oracle" in html
    assert (out / "alerts.csv").exists() and (out / "overall.csv").exists()


def test_fit_then_evaluate_round_trip(dataset_dir, tmp_path):
    model = tmp_path / "cusum.json"
    res = runner.invoke(app, ["fit", "--method", "cusum", "--data", str(dataset_dir), "--out", str(model)])
    assert res.exit_code == 0, res.output
    det = load(model)
    out = tmp_path / "eval"
    res = runner.invoke(app, ["evaluate", "--model", str(model), "--data", str(dataset_dir), "--out", str(out)])
    assert res.exit_code == 0, res.output
    scores = pd.read_parquet(out / "scores.parquet")
    flights = pd.read_parquet(dataset_dir / "flights.parquet")
    assert np.array_equal(scores.score.to_numpy(), det.decision_function(flights))
    assert np.array_equal(scores.alarm.to_numpy(), (scores.score > det.threshold_).astype(int).to_numpy())
    r = json.loads((out / "results.json").read_text())
    assert 0.0 <= r["metrics"]["f1"] <= 1.0 and r["threshold"] == det.threshold_
    res = runner.invoke(app, ["evaluate", "--model", str(model), "--data", str(dataset_dir),
                              "--out", str(tmp_path / "e2"), "--test-only"])
    assert res.exit_code == 0
    assert pd.read_parquet(tmp_path / "e2" / "scores.parquet").flight_id.nunique() == len(det.calibration_["test_flights"])


@pytest.mark.parametrize("args, message", [
    (["benchmark", "--profile", "huge"], "profile: unknown profile 'huge'"),
    (["benchmark", "--methods", "chi2,nope"], "unknown detector 'nope'"),
    (["resilience", "--threshold", "x"], "threshold: unknown choice"),
    (["resilience", "--max-flights", "0"], "max-flights: must be at least 1"),
    (["fit", "--method", "cusum", "--data", "/nonexistent", "--out", "m.json"], "no such dataset"),
    (["evaluate", "--model", "/nonexistent.json", "--data", ".", "--out", "x"], "no such model file"),
])
def test_cli_errors(args, message, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    res = runner.invoke(app, args)
    assert res.exit_code == 2
    assert message in res.output
