"""The demo's run through the library: a profile's datasets, the detection benchmark, then
the resilience benchmark, on a cache holding one small dataset per configuration."""

from __future__ import annotations

import json
import shutil

import pytest

from quadformer.experiments.cache import dataset_key
from quadformer.experiments.demo import run_demo_profile
from quadformer.experiments.grid import PROFILES, profile_configs, select_configs


@pytest.fixture(scope="module")
def short_dataset_dir(short_dataset, tmp_path_factory):
    """6 flights of 10 s, half of them attacked (bias from 2.5-4 s for 2.5-4 s)."""
    from quadformer.dataset import write_dataset

    return write_dataset(short_dataset, tmp_path_factory.mktemp("short") / "ds")


def test_demo_run_benchmarks_detection_then_resilience_from_the_cache(short_dataset_dir, tmp_path):
    part = select_configs(PROFILES["demo"], "modelII-laplace-bias")
    cache = tmp_path / "cache"
    for name, cfg in profile_configs(part):
        shutil.copytree(short_dataset_dir, cache / f"{name}-{dataset_key(cfg)}")
    out = tmp_path / "demo"
    run = run_demo_profile(out, cache, ["cusum"], profile=part, detector="cusum", progress=False, workers=1)
    assert [r["config"] for r in run.datasets] == ["modelII-laplace-bias"] and run.datasets[0]["flights"] == 6
    assert list(run.phases) == ["simulate", "detection", "resilience"] and min(run.phases.values()) >= 0
    written = json.loads((out / "detection" / "results.json").read_text())
    assert [c["name"] for c in run.detection["configs"]] == [c["name"] for c in written["configs"]] == [
        "modelII-laplace-bias"]
    assert run.resilience["detector"] == "cusum" and (out / "resilience" / "alerts.csv").exists()
    assert run.resilience["configs"][0]["model_from_cache"] is True      # the detection run's tuned CUSUM
    assert sorted(p.name for p in cache.iterdir() if p.name != "models") == [
        f"{n}-{dataset_key(c)}" for n, c in profile_configs(part)]       # nothing simulated


def test_the_demo_on_shipped_detectors_trains_nothing_and_scores_every_flight(short_dataset_dir, tmp_path):
    """The default demo: the shipped vio detectors score every flight of a configuration's new
    dataset, the shipped QUADFormer drives the resilient estimator, and `detect`'s route reads
    simulated PX4 and ArduPilot logs (a vehicle without a camera under a consistent drift among
    them) with the shipped detector it picks."""
    from quadformer.detectors import pretrained
    from quadformer.experiments.demo import run_shipped_demo, shipped_profile

    part = select_configs(shipped_profile(), "modelII-laplace-bias")
    cache = tmp_path / "cache"
    for name, cfg in profile_configs(part):
        shutil.copytree(short_dataset_dir, cache / f"{name}-{dataset_key(cfg)}")
    out = tmp_path / "demo"
    # logs of 6 s: the route from the written logs to their scores is tested, not what the detector finds
    # in them (the two log simulations take the phase's time, which goes with the flights' length)
    run = run_shipped_demo(out, cache, progress=False, workers=1, profile=part, fly=1, log_duration=6.0)
    assert list(run.phases) == ["simulate", "detection", "resilience", "logs"]
    cfg = run.detection["configs"][0]
    assert cfg["split"]["test"] == cfg["n_test_flights"] == 6 and cfg["split"]["train"] == 0
    assert set(cfg["methods"]) == set(run.shipped) >= {"quadformer", "cusum", "chi2"}
    assert all(m["model_from_cache"] for m in cfg["methods"].values())          # nothing tuned
    assert run.detection["shipped"]["quadformer"] == "vio-quadformer"
    assert "shipped detectors" in run.detection["protocol"]
    res = run.resilience["configs"][0]
    assert run.resilience["shipped"] == "vio-quadformer" and res["test_flights"] == 1
    assert [o.status for o in run.logs.outcomes] == ["scored"] * 6               # three flights, two formats
    assert sorted(o.path.name for o in run.logs.outcomes) == [
        "drift_0000.bin", "drift_0000.ulg", "flight_0000.bin", "flight_0000.ulg", "flight_0001.bin", "flight_0001.ulg"]
    assert run.log_detector == pretrained.sets()["magbaro"].default
    assert (out / "logs" / "summary.csv").exists() and (out / "detection" / "report.html").exists()
    assert json.loads((out / "detection" / "results.json").read_text())["methods_run"] == list(run.shipped)
