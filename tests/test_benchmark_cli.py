"""End to end: benchmark, fit and evaluate through the CLI, as a user runs them."""

import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from quadformer.cli import app
from quadformer.detectors import load
from quadformer.detectors.attack_types import SHAPE_TYPES
from quadformer.dataset import write_dataset
from quadformer.experiments.cache import dataset_key
from quadformer.experiments.grid import PROFILES, profile_configs

runner = CliRunner()


@pytest.fixture(scope="module")
def dataset_dir(bias_dataset, tmp_path_factory):
    return write_dataset(bias_dataset, tmp_path_factory.mktemp("data") / "ds")


@pytest.fixture(scope="module")
def short_dataset_dir(short_dataset, tmp_path_factory):
    """The short dataset (conftest): the resilience run flies its test flights again under four
    policies for each of the profile's configurations, and the stress run scores a copy of it
    for each of the configurations' stress sets, so the flights' length sets the tests' time."""
    return write_dataset(short_dataset, tmp_path_factory.mktemp("short") / "ds")


def _fill(cache, named_configs, dataset_dir):
    """The cache filled with one small real dataset under each named config's key (the
    harness is tested, not the simulator)."""
    for name, cfg in named_configs:
        path = cache / f"{name}-{dataset_key(cfg)}"
        if not path.exists():
            shutil.copytree(dataset_dir, path)


@pytest.fixture(scope="module")
def demo_bench(short_dataset_dir, tmp_path_factory):
    """The demo profile benchmarked once through the CLI with chi2 and CUSUM and its stress
    sets, on a cache holding the short dataset under every configuration's and stress set's
    key, so the test exercises the harness without simulating: a stress run is the benchmark
    run with the stress sets scored as well, so its outputs are read by the tests of both.
    Also the modification times of the cache's datasets before the run. A test that runs
    more on the cache copies it first."""
    from quadformer.experiments.stress import stress_configs

    root = tmp_path_factory.mktemp("demo-bench")
    cache, out = root / "cache", root / "bench"
    configs = profile_configs(PROFILES["demo"])
    _fill(cache, configs, short_dataset_dir)
    for name, cfg in configs:
        _fill(cache, [(n, c) for n, _, c in stress_configs(name, cfg, PROFILES["demo"].stress_flights)],
              short_dataset_dir)
    before = {p: p.stat().st_mtime for p in cache.rglob("flights.parquet")}
    res = runner.invoke(app, ["benchmark", "--profile", "demo", "--methods", "chi2,cusum", "--stress", "--cache",
                              str(cache), "--out", str(out), "--quiet", "--workers", "1"])
    return SimpleNamespace(res=res, cache=cache, out=out, before=before)


def test_benchmark_writes_schema_tables_report_and_reuses_cache(demo_bench):
    res, cache, out = demo_bench.res, demo_bench.cache, demo_bench.out
    assert res.exit_code == 0, res.output
    assert "Model I" in res.output and "Model II" in res.output and "report.html" in res.output
    assert demo_bench.before == {p: p.stat().st_mtime for p in cache.rglob("flights.parquet")}   # reused

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
    assert (out / "figures" / "f1_by_config.png").exists() and (out / "figures" / "delay_vs_false_alarms.png").exists()
    # the report opens with its figures; the tables follow in sections that fold
    assert html.index("At a glance") < html.index("data:image/png;base64,") < html.index("<table")
    assert html.index("<details open><summary>") < html.index("<table")
    alerts = pd.read_csv(out / "alerts.csv")
    assert {"config", "method", "flight_id", "start_s", "onset_s", "attack_type", "score",
            "end_s"} <= set(alerts.columns)
    assert set(alerts.method) <= {"chi2", "cusum"} and len(alerts) > 0
    assert len(list((cache / "models").rglob("cusum-*.tuned.json"))) == 8      # tuned detectors cached


def test_resilience_cli_flies_four_policies_and_reuses_tuned_detectors(demo_bench, tmp_path):
    assert demo_bench.res.exit_code == 0, demo_bench.res.output
    cache = tmp_path / "cache"
    shutil.copytree(demo_bench.cache, cache)                 # the datasets and the CUSUMs the benchmark tuned
    out = tmp_path / "res"
    args = ["--profile", "demo", "--cache", str(cache), "--quiet", "--workers", "1"]     # no worker to spawn
    res = runner.invoke(app, ["resilience", "--detector", "cusum", "--out", str(out), *args])
    assert res.exit_code == 0, res.output
    assert "naive" in res.output and "oracle" in res.output and "alerts.csv" in res.output
    r = json.loads((out / "results.json").read_text())
    assert r["policies"] == ["naive", "px4", "resilient", "oracle"]
    # the demo profile's resilience run flies its four resilience configurations
    assert [(c["model"], c["noise"], c["attack"]) for c in r["configs"]] == list(PROFILES["demo"].resilience_grid)
    c = r["configs"][0]
    assert c["model_from_cache"] is True                 # the benchmark's tuned CUSUM, not a new one
    assert set(c["policies"]) == set(r["policies"])
    for p in r["policies"]:
        assert c["policies"][p]["attacked_flights"] + c["policies"][p]["clean_flights"] == c["test_flights"]
    assert c["policies"]["oracle"]["wrongly_excluded_fraction"] == 0.0
    assert c["policies"]["naive"]["excluded_during_attack"] == 0
    # detection in the closed loop: GPS excluded against GPS spoofed, point-wise
    for cc in r["configs"]:
        if cc["policies"]["oracle"]["attacked_flights"]:
            assert cc["policies"]["oracle"]["exclusion_f1"] == 1.0
        assert cc["policies"]["naive"]["exclusion_f1"] == 0.0
    assert "exclusion F1" in pd.read_csv(out / "overall.csv").columns
    traj = pd.read_parquet(out / "trajectories" / f"{c['name']}.parquet")
    assert len(traj) == 4 * c["test_flights"] * 100           # 10 s at 10 Hz
    html = (out / "report.html").read_text()
    assert html.count("data:image/png;base64,") >= 1 and "oracle" in html
    assert (out / "alerts.csv").exists() and (out / "overall.csv").exists()
    # the resilient flights' alerts (none on these short flights), with the type confirmed 5 s later
    assert "confirmed_type" in pd.read_csv(out / "alerts.csv").columns


def test_configs_selects_part_of_a_profile_with_the_whole_profiles_datasets_and_models(short_dataset_dir,
                                                                                          tmp_path):
    """--configs runs some configurations of a profile: only their datasets are needed (the
    cache holds no other, and nothing is simulated), in the profile's order; the resilience
    run flies the selection with the detector the benchmark tuned."""
    whole = dict(profile_configs(PROFILES["demo"]))
    picked = ["modelII-laplace-bias", "modelI-exponential-ramp"]
    cache = tmp_path / "cache"
    for name in picked:
        shutil.copytree(short_dataset_dir, cache / f"{name}-{dataset_key(whole[name])}")
    args = ["--profile", "demo", "--cache", str(cache), "--quiet", "--workers", "1", "--configs", ",".join(picked)]
    res = runner.invoke(app, ["benchmark", "--methods", "cusum", "--out", str(tmp_path / "bench"), *args])
    assert res.exit_code == 0, res.output
    r = json.loads((tmp_path / "bench" / "results.json").read_text())
    assert [c["name"] for c in r["configs"]] == ["modelI-exponential-ramp", "modelII-laplace-bias"]
    assert sorted(p.name for p in cache.iterdir() if p.name != "models") == sorted(
        f"{n}-{dataset_key(whole[n])}" for n in picked)
    res = runner.invoke(app, ["resilience", "--detector", "cusum", "--out", str(tmp_path / "res"), *args[:-1],
                              "modelII-laplace-bias", "--max-flights", "1"])
    assert res.exit_code == 0, res.output
    r = json.loads((tmp_path / "res" / "results.json").read_text())
    assert [c["name"] for c in r["configs"]] == ["modelII-laplace-bias"]
    assert r["configs"][0]["model_from_cache"] is True


def test_select_configs_keeps_each_configuration_as_in_the_whole_profile():
    from quadformer.experiments.grid import select_configs

    demo = PROFILES["demo"]
    part = select_configs(demo, "modelII-laplace-bias, modelI-exponential-ramp,modelII-laplace-bias")
    assert part.grid == (("I", "exponential", "ramp"), ("II", "laplace", "bias"))
    assert dict(profile_configs(part)) == {n: c for n, c in profile_configs(demo) if n in dict(profile_configs(part))}
    # the resilience run flies the selected configurations of the profile's resilience grid,
    # or the selection when it holds none of them
    assert part.for_resilience().grid == (("II", "laplace", "bias"),)
    assert select_configs(demo, "modelI-exponential-ramp").for_resilience().grid == (("I", "exponential", "ramp"),)
    assert select_configs(PROFILES["quick"], "modelI-laplace-ramp").for_resilience().grid == (
        ("I", "laplace", "ramp"),)


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
    scored = pd.read_parquet(tmp_path / "e2" / "scores.parquet")
    assert scored.flight_id.nunique() == len(det.calibration_["test_flights"])


@pytest.mark.parametrize("args, message", [
    (["benchmark", "--profile", "huge"], "profile: unknown profile 'huge'"),
    (["benchmark", "--methods", "chi2,nope"], "unknown detector 'nope'"),
    (["resilience", "--threshold", "x"], "threshold: unknown choice"),
    (["resilience", "--max-flights", "0"], "max-flights: must be at least 1"),
    (["benchmark", "--seeds", "0"], "seeds: must be at least 1"),
    (["benchmark", "--seeds", "2", "--seed-list", "0,1"], "give --seeds or --seed-list, not both"),
    (["benchmark", "--seed-list", "0,x"], "seed-list: expected comma-separated integers"),
    (["benchmark", "--seed-list", "1,1"], "seed-list: expected distinct non-negative integers"),
    (["benchmark", "--data", "x", "--stress"], "need a profile"),
    (["benchmark", "--profile", "quick", "--configs", "modelIII-exponential-bias"],
     "configs: 'modelIII-exponential-bias' not in profile 'quick'; choose from modelI-exponential-bias"),
    (["benchmark", "--data", "x", "--configs", "modelI-exponential-bias"], "with --data the datasets are given"),
    (["resilience", "--configs", " , "], "configs: no configuration named"),
    (["fit", "--method", "cusum", "--data", "/nonexistent", "--out", "m.json"], "no such dataset"),
    (["evaluate", "--model", "/nonexistent.json", "--data", ".", "--out", "x"], "no such model file"),
])
def test_cli_errors(args, message, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    res = runner.invoke(app, args)
    assert res.exit_code == 2
    assert message in res.output



# -- mixed profile, stress sets, several seeds ------------------------------------------------

import dataclasses  # noqa: E402

from quadformer.config import MIX_KINDS, AttackConfig, SimConfig  # noqa: E402
from quadformer.experiments.grid import config_seed  # noqa: E402
from quadformer.experiments.stress import STRESS_SETS, stress_configs  # noqa: E402


def test_paper_grid_keys_and_seeds_are_unchanged_and_the_mixed_profile_has_its_own():
    """The seeds of the paper's configurations are those recorded before mixed attacks and the
    mixed profile existed; their dataset keys are those of dataset format version 3 (the
    persistent residues: a cached dataset without their columns is simulated again)."""
    quick = dict(profile_configs(PROFILES["quick"]))
    assert {n: (c.seed, dataset_key(c)) for n, c in quick.items()} == {
        "modelI-exponential-bias": (3864535762, "f6c894a94a017efc"),
        "modelI-exponential-ramp": (284361292, "09eeb89d47fa6e58"),
        "modelI-laplace-bias": (213587156, "9a4df0e555a7861f"),
        "modelI-laplace-ramp": (2607961550, "616546cff98a14ed"),
        "modelII-exponential-bias": (1515697190, "9bb3b40950073ba6"),
        "modelII-exponential-ramp": (4077715072, "27fe0554bd9f3c2a"),
        "modelII-laplace-bias": (2584796953, "b55909396ce269a8"),
        "modelII-laplace-ramp": (1603077921, "ed8db160fbd30607"),
    }
    mixed = profile_configs(PROFILES["mixed"])
    assert [n for n, _ in mixed] == ["modelI-exponential-mix", "modelI-laplace-mix", "modelII-exponential-mix",
                                     "modelII-laplace-mix"]
    seeds = [c.seed for _, c in mixed]
    assert len(set(seeds)) == 4 and not set(seeds) & {c.seed for c in quick.values()}
    for _, c in mixed:
        assert c.flights == 60 and c.attack.kind == "mix" and c.attack.mix == MIX_KINDS
        assert c.attack.magnitude is None            # each kind draws from its own ranges
    assert config_seed(0, "I", "laplace", "mix") == mixed[1][1].seed
    assert config_seed(1, "I", "laplace", "mix") != mixed[1][1].seed


def test_stress_sets_pair_with_the_tuning_attack_and_leave_its_ranges():
    cfg = dict(profile_configs(PROFILES["quick"]))
    bias = stress_configs("b", cfg["modelI-exponential-bias"], 24)
    ramp = stress_configs("r", cfg["modelII-laplace-ramp"], 24)
    assert [st.name for _, st, _ in bias] == ["small-offsets", "long-bias", "freeze", "replay", "intermittent",
                                              "gaussian-noise"]
    assert [st.name for _, st, _ in ramp] == ["slow-drifts", "long-ramp", "sinusoid", "gaussian-noise"]
    assert len(stress_configs("m", SimConfig(attack=AttackConfig(kind="mix")), 24)) == len(STRESS_SETS)
    by = {st.name: c for _, st, c in bias + ramp}
    for _, _, c in bias + ramp:
        assert c.flights == 24 and c.attack.fraction == 0.5
    assert by["small-offsets"].attack.magnitude == (1.0, 1.5)        # tuning: 1.5-6 m
    assert by["slow-drifts"].attack.rate == (0.05, 0.2)              # tuning: 0.2-1 m/s
    for name in ("long-bias", "long-ramp"):
        assert by[name].duration == 90.0 and by[name].attack.duration == (30.0, 60.0)
        assert by[name].attack.onset[1] + by[name].attack.duration[1] <= by[name].duration
    g = [c for _, st, c in ramp if st.name == "gaussian-noise"][0]
    assert g.noise == "gaussian" and g.attack == cfg["modelII-laplace-ramp"].attack and g.model == "II"
    seeds = [c.seed for _, _, c in bias]
    assert len(set(seeds)) == len(seeds) and cfg["modelI-exponential-bias"].seed not in seeds
    assert {c.model for _, _, c in bias} == {"I"}


def test_benchmark_stress_scores_the_tuned_detectors_on_stress_sets(demo_bench):
    from quadformer.dataset import load_dataset
    from quadformer.evaluation.metrics import evaluate
    from quadformer.experiments.cache import model_dir_for

    res, cache, out = demo_bench.res, demo_bench.cache, demo_bench.out
    assert res.exit_code == 0, res.output
    assert "Stress sets" in res.output and "slow-drifts" in res.output and "Model I" in res.output
    r = json.loads((out / "results.json").read_text())
    st = r["stress"]
    assert st["flights_per_set"] == 12 and set(st["sets"]) == {s.name for s in STRESS_SETS}
    assert set(st["configs"]["modelI-exponential-bias"]) == {"small-offsets", "long-bias", "freeze", "replay",
                                                             "intermittent", "gaussian-noise"}
    assert set(st["configs"]["modelI-exponential-ramp"]) == {"slow-drifts", "long-ramp", "sinusoid",
                                                             "gaussian-noise"}
    pooled = st["pooled"]["small-offsets"]["cusum"]
    assert pooled["configs"] == 4
    for k in ("event_recall", "delay_median_s", "false_alarms_per_hour", "f1", "vus_pr", "event_recall_by_type"):
        assert k in pooled
    # the stress scores are those of the tuned (cached) detector on the stress flights
    name = "modelI-exponential-bias"
    path = Path(r["configs"][0]["dataset"])
    from quadformer.detectors import load

    model = next(p for p in model_dir_for(cache, path, 0, 0.2).glob("cusum-*.json") if ".tuned." not in p.name)
    det = load(model)
    entry = st["configs"][name]["small-offsets"]
    f = load_dataset(entry["dataset"]).flights
    s = det.decision_function(f)
    want = evaluate(f.flight_id.to_numpy(), f.t.to_numpy(), f.label.to_numpy(), s, s > det.threshold_)
    assert entry["methods"]["cusum"]["f1"] == want["f1"]
    assert entry["methods"]["cusum"]["event_recall"] == want["event_recall"]
    # and at the false-alarm budget threshold chosen on the main run's validation flights
    assert det.budget_threshold_ is not None
    at_budget = evaluate(f.flight_id.to_numpy(), f.t.to_numpy(), f.label.to_numpy(), s, s > det.budget_threshold_,
                         vus=False)
    for k in ("event_recall", "false_alarms_per_hour", "f1", "delay_median_s"):
        assert entry["methods"]["cusum"]["budget"][k] == at_budget[k]
    assert set(pooled["budget"]) >= {"event_recall", "false_alarms_per_hour", "delay_median_s"}
    assert "budget: event recall" in res.output
    html = (out / "report.html").read_text()
    assert "Stress evaluation" in html and (out / "stress.csv").exists()
    # per-type recall and type confusion for every method (non-classifiers predict "attack")
    m = r["configs"][0]["methods"]["chi2"]
    assert set(m["event_recall_by_type"]) <= {"bias"} and "vus_pr" in m
    assert all(set(row) <= {"attack"} for row in m["type_confusion"].values())
    lo, hi = m["f1_ci95"]
    assert 0.0 <= lo <= hi <= 1.0
    assert "Event recall per attack type" in html and "VUS-PR" in html


@pytest.fixture(scope="module")
def mixed_dir(tmp_path_factory):
    from quadformer.simulation import simulate

    # 12 s flights (attacks of 3-5 s from 3-5 s): five kinds among the six attacked flights, a
    # freeze among the test flights
    cfg = SimConfig(model="II", noise="laplace", flights=10, duration=12.0, seed=9,
                    attack=AttackConfig(kind="mix", onset=(3.0, 5.0), duration=(3.0, 5.0), fraction=0.6))
    return write_dataset(simulate(cfg), tmp_path_factory.mktemp("mixdata") / "ds")


def test_benchmark_mixed_profile_reports_types(mixed_dir, tmp_path):
    cache = tmp_path / "cache"
    _fill(cache, profile_configs(PROFILES["mixed"]), mixed_dir)
    out = tmp_path / "bench"
    res = runner.invoke(app, ["benchmark", "--profile", "mixed", "--methods", "chi2,cusum", "--cache", str(cache),
                              "--out", str(out), "--quiet", "--workers", "1"])
    assert res.exit_code == 0, res.output
    assert "exp-mixed-F1" in res.output
    r = json.loads((out / "results.json").read_text())
    assert r["profile"] == "mixed" and [c["attack"] for c in r["configs"]] == ["mix"] * 4
    csv = pd.read_csv(out / "table_model_I.csv", index_col=0)
    assert csv.shape == (2, 6)
    from quadformer.dataset import load_dataset
    from quadformer.evaluation.protocol import split_flights

    sc = load_dataset(mixed_dir).scenarios
    assert len(set(sc.attack_type[sc.attacked])) >= 2                   # several kinds in the data
    test = sc[sc.flight_id.isin(split_flights(sc, 0).test) & sc.attacked]
    for c in r["configs"]:   # the windows per type are those of the attacked test flights' own kinds
        assert set(c["methods"]["cusum"]["event_recall_by_type"]) == set(test.attack_type)
        assert sum(v["windows"] for v in c["methods"]["chi2"]["event_recall_by_type"].values()) >= len(test)
    recall = pd.read_csv(out / "event_recall_by_type.csv", index_col=0)
    assert list(recall.index) == ["chi2", "cusum"] and set(recall.columns) == set(test.attack_type)
    # every detector's alarms typed by shape, at the first step of each alarm run and 5 s later
    for c in r["configs"]:
        for m in ("chi2", "cusum"):
            got = c["methods"][m]
            assert set(got["type_confusion"]) == set(got["type_confusion_shape"]) == \
                set(got["type_confusion_shape_confirmed"])
            assert sum(map(sum, (row.values() for row in got["type_confusion_shape"].values()))) == \
                sum(map(sum, (row.values() for row in got["type_confusion"].values())))
            assert all(set(row) <= set(SHAPE_TYPES) for row in got["type_confusion_shape"].values())
    html = (out / "report.html").read_text()
    assert "Attack typing at alarms" in html and "shape typer at the first alarm" in html
    typing = pd.read_csv(out / "typing.csv", index_col=0)
    assert list(typing.index) == ["chi2", "cusum"]
    assert list(typing.columns) == ["shape typer at the first alarm", "shape typer, confirmed 5 s later"]
    assert "Attacks typed right, of the detected attacks" in res.output
    # per detected attack: one per attacked test flight with an alarm on an attacked step
    for c in r["configs"]:
        t = c["methods"]["chi2"]["attack_typing"]
        assert t["own"] is None and t["shape_first"]["attacks"] == t["shape_confirmed"]["attacks"]
        found = sum(v["found"] for v in c["methods"]["chi2"]["event_recall_by_type"].values())
        assert 0 < t["shape_first"]["attacks"] <= min(len(test), found)
        assert 0 <= t["shape_first"]["right"] <= t["shape_first"]["attacks"]


def test_benchmark_over_seeds_keeps_each_run_and_the_spread(short_dataset_dir, tmp_path):
    # two of the profile's configurations (the spread is per configuration; each one more would
    # add two entries tuned and scored, nothing else), on the short flights: 4 entries
    from quadformer.experiments.grid import select_configs

    picked = "modelI-exponential-bias,modelII-laplace-ramp"
    cache = tmp_path / "cache"
    for s in (0, 1):
        _fill(cache, profile_configs(dataclasses.replace(select_configs(PROFILES["demo"], picked), seed=s)),
              short_dataset_dir)
    out = tmp_path / "seeds"
    res = runner.invoke(app, ["benchmark", "--profile", "demo", "--configs", picked, "--methods", "chi2,cusum",
                              "--seeds", "2", "--cache", str(cache), "--out", str(out), "--quiet", "--workers", "1"])
    assert res.exit_code == 0, res.output
    assert "over seeds 0, 1" in res.output and "±" in res.output
    r = json.loads((out / "results.json").read_text())
    assert r["seeds"] == [0, 1] and set(r["per_seed"]) == {"0", "1"}
    assert (r["provenance"]["seeds"], r["provenance"]["profile"]) == ({"runs": [0, 1]}, "demo")
    runs = [json.loads((out / f"seed-{s}" / "results.json").read_text()) for s in (0, 1)]
    assert [x["seed"] for x in runs] == [0, 1] and [x["dataset_seed"] for x in runs] == [0, 1]
    assert [x["provenance"]["seeds"] for x in runs] == [{"dataset": 0, "split": 0}, {"dataset": 1, "split": 1}]
    assert runs[0]["configs"][0]["dataset"] != runs[1]["configs"][0]["dataset"]     # own datasets per seed
    name = runs[0]["configs"][0]["name"]
    f1 = [x["configs"][0]["methods"]["cusum"]["f1"] for x in runs]
    summ = r["summary"][name]["cusum"]["f1"]
    assert summ["n"] == 2 and summ["mean"] == pytest.approx(np.mean(f1))
    assert summ["std"] == pytest.approx(np.std(f1, ddof=1)) and (summ["min"], summ["max"]) == (min(f1), max(f1))
    assert r["per_seed"]["1"][name]["cusum"]["f1"] == f1[1]
    df = pd.read_csv(out / "seeds_f1.csv", index_col=0)
    assert list(df.index) == ["chi2", "cusum"] and list(df.columns) == [c["name"] for c in runs[0]["configs"]]
    assert sorted(df.columns) == sorted(picked.split(","))
    assert (out / "report.html").exists() and (out / "seed-1" / "report.html").exists()
