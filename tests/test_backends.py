"""Work units on a backend: the local process pool and Ray give the same figures, cache
entries are built once and never read half-written when several processes want them, a
failed unit is named and the others' results are kept, and the training device is checked."""

from __future__ import annotations

import json
import math
import multiprocessing
import os
import shutil
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
import torch
from typer.testing import CliRunner

import quadformer
from quadformer.cli import app
from quadformer.config import AttackConfig, SimConfig
from quadformer.dataset import DatasetError, load_dataset, write_dataset
from quadformer.evaluation.protocol import TrainingBudget
from quadformer.detectors.classical import Cusum
from quadformer.experiments.cache import (cached_model, dataset_key, detector_sources, detectors_digest,
                                          ensure_configs, model_dir_for, simulate_dataset, tune_unit)
from quadformer.experiments.detection import run_benchmark
from quadformer.experiments.grid import PAPER_GRID, Profile, profile_configs
from quadformer.experiments.pool import Backend, UnitError, run_jobs

runner = CliRunner()

#: a tenth of every trained method's epochs and windows: these tests check where and how
#: units run and networks are saved and loaded, not how well they learn
BUDGET = TrainingBudget("tiny", 0.1)
#: two of the paper's configurations, sized by the datasets copied into the cache
TINY = Profile("tiny", 6, grid=PAPER_GRID[:2], budget=BUDGET)
#: a dataset simulated in a second or two (the simulator's time goes with the flights' length); the tests
#: compare and race on its files, not on what is in them
SMALL = SimConfig(model="I", noise="laplace", flights=2, duration=3.0, seed=5,
                  attack=AttackConfig(kind="bias", onset=(1.0, 1.5), duration=(1.0, 1.5)))
#: what changes from run to run whatever the backend: timings, paths, versions
VOLATILE = {"tune_seconds", "score_seconds", "timing_s", "versions", "dataset"}


@pytest.fixture(scope="module")
def ray_runtime():
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False)
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def dataset_dir(bias_dataset, tmp_path_factory):
    return write_dataset(bias_dataset, tmp_path_factory.mktemp("data") / "ds")


def _fill(cache: Path, profile: Profile, dataset_dir: Path) -> None:
    """The cache filled with one small real dataset under each configuration's key."""
    for name, cfg in profile_configs(profile):
        shutil.copytree(dataset_dir, cache / f"{name}-{dataset_key(cfg)}")


def _stable(obj):
    if isinstance(obj, dict):
        return {k: _stable(v) for k, v in obj.items() if k not in VOLATILE}
    if isinstance(obj, list):
        return [_stable(v) for v in obj]
    return obj


def test_same_seed_gives_the_same_datasets_and_figures_locally_and_on_ray(ray_runtime, dataset_dir, tmp_path):
    ray_backend = Backend("ray")
    local = ensure_configs([("small", SMALL)], tmp_path / "sim-local", progress=False, workers=2)["small"]
    on_ray = ensure_configs([("small", SMALL)], tmp_path / "sim-ray", progress=False, backend=ray_backend)["small"]
    pd.testing.assert_frame_equal(load_dataset(local).flights, load_dataset(on_ray).flights)
    pd.testing.assert_frame_equal(load_dataset(local).scenarios, load_dataset(on_ray).scenarios)

    runs = {}
    for name, backend in (("local", Backend()), ("ray", ray_backend)):
        cache = tmp_path / f"cache-{name}"
        _fill(cache, TINY, dataset_dir)
        runs[name] = run_benchmark(TINY, ["chi2", "cusum", "cnn"], tmp_path / f"out-{name}", cache, progress=False,
                                   workers=2, label_fraction=1.0, backend=backend, device="cpu")
    a, b = (json.loads((tmp_path / f"out-{n}" / "results.json").read_text()) for n in ("local", "ray"))
    assert len(a["configs"]) == 2 and a["configs"][0]["methods"]["cnn"]["model_from_cache"] is False
    assert 0.0 <= a["configs"][0]["methods"]["cnn"]["f1"] <= 1.0
    assert _stable(a) == _stable(b)
    for name, _ in profile_configs(TINY):
        pd.testing.assert_frame_equal(pd.read_parquet(tmp_path / "out-local" / "scores" / f"{name}.parquet"),
                                      pd.read_parquet(tmp_path / "out-ray" / "scores" / f"{name}.parquet"))


def test_a_failed_unit_is_named_and_the_others_run_on_ray(ray_runtime):
    with pytest.raises(UnitError) as err:
        run_jobs(math.sqrt, [(4.0,), (-1.0,), (9.0,)], progress=False, backend=Backend("ray"),
                 labels=["config a, seed 0", "config b, seed 1", "config c, seed 2"])
    msg = str(err.value)
    assert "1 of 3 work unit(s) failed" in msg and "config b, seed 1: ValueError: math domain error" in msg
    assert [label for label, _ in err.value.failures] == ["config b, seed 1"]


def test_a_failed_tuning_unit_is_named_and_a_rerun_does_only_what_is_missing(dataset_dir, tmp_path):
    cache = tmp_path / "cache"
    _fill(cache, TINY, dataset_dir)
    # QUADFormer (supervised) refuses to train without a labelled flight; CUSUM needs no label (the
    # units run in this process: the local pool's failed units are named in the next test)
    with pytest.raises(UnitError) as err:
        run_benchmark(TINY, ["cusum", "quadformer"], tmp_path / "out", cache, progress=False, workers=1,
                      label_fraction=0.0, device="cpu")
    msg = str(err.value)
    assert "tune: 2 of 4 work unit(s) failed" in msg
    assert "config modelI-exponential-bias, seed 0, method quadformer: ValueError: no labelled training flight" in msg
    assert "config modelI-exponential-ramp, seed 0, method quadformer" in msg
    for name, cfg in profile_configs(TINY):
        model_dir = model_dir_for(cache, cache / f"{name}-{dataset_key(cfg)}", 0, 0.0)
        assert cached_model("cusum", 1.0, model_dir, BUDGET) is not None      # kept
        assert cached_model("quadformer", 1.0, model_dir, BUDGET) is None
    res = run_benchmark(TINY, ["cusum"], tmp_path / "out", cache, progress=False, workers=1, label_fraction=0.0)
    assert [c["methods"]["cusum"]["model_from_cache"] for c in res["configs"]] == [True, True]


def test_units_failing_in_local_workers_are_named_after_every_unit_ran():
    with pytest.raises(UnitError) as err:
        run_jobs(math.sqrt, [(-1.0,), (4.0,), (-2.0,)], workers=2, progress=False,
                 labels=["config a, seed 0", "config b, seed 0", "config c, seed 0"])
    assert [label for label, _ in err.value.failures] == ["config a, seed 0", "config c, seed 0"]
    assert run_jobs(math.sqrt, [(4.0,), (9.0,)], workers=2, progress=False) == [2.0, 3.0]


# -- several processes on one cache entry ---------------------------------------------------

def _writer(path: Path, barrier, results) -> None:
    """One worker of a run: the dataset unit, then the CUSUM tuning unit, on the same entry."""
    torch.set_num_threads(1)
    barrier.wait()
    wrote = simulate_dataset(SMALL, path)
    tuned = tune_unit(path, "cusum", 0, 0.5, 1.0, path.parent / "models", "cpu")
    results.put((wrote, tuned["cached"]))


def _reader(path: Path, stop, results) -> None:
    """Reads the entries as fast as it can: each read is either 'not there' or complete."""
    seen = {"missing": 0, "complete": 0, "model": 0}
    bad = []
    while True:
        done = stop.is_set()
        try:
            ds = load_dataset(path)
            assert ds.flights.flight_id.nunique() == SMALL.flights and len(ds.scenarios) == SMALL.flights
            seen["complete"] += 1
        except DatasetError as e:
            if "no such dataset directory" in str(e):
                seen["missing"] += 1
            else:
                bad.append(str(e))
        except Exception as e:   # a half-written file read as a whole
            bad.append(f"{type(e).__name__}: {e}")
        if (path.parent / "models").exists() and cached_model("cusum", 1.0, path.parent / "models") is not None:
            seen["model"] += 1
        if done:
            break
        time.sleep(0.005)   # leave the cores to the writers
    results.put((seen, bad))


def test_concurrent_writers_build_a_cache_entry_once_and_readers_never_see_it_partial(tmp_path):
    ctx = multiprocessing.get_context("spawn")
    path = tmp_path / "cache" / f"small-{dataset_key(SMALL)}"
    n = 3
    barrier, stop = ctx.Barrier(n), ctx.Event()
    wq, rq = ctx.Queue(), ctx.Queue()
    reader = ctx.Process(target=_reader, args=(path, stop, rq))
    reader.start()
    writers = [ctx.Process(target=_writer, args=(path, barrier, wq)) for _ in range(n)]
    for w in writers:
        w.start()
    # the queues and processes say when each has finished; the timeouts are only a safety net
    # for a hung process, ten times what a loaded 2-core machine needs
    outcomes = [wq.get(timeout=600) for _ in range(n)]
    for w in writers:
        w.join(timeout=300)
        assert w.exitcode == 0
    stop.set()
    seen, bad = rq.get(timeout=300)
    reader.join(timeout=300)
    assert bad == []
    assert seen["complete"] >= 1 and seen["model"] >= 1
    assert sorted(w for w, _ in outcomes) == [False] * (n - 1) + [True]     # simulated once
    assert sorted(c for _, c in outcomes) == [False] + [True] * (n - 1)     # tuned once
    leftovers = [p.name for p in path.parent.rglob("*") if p.name.endswith((".lock", ".tmp"))]
    assert leftovers == []


# -- training device and backend choice ------------------------------------------------------

@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_cuda_without_a_gpu_is_a_clear_error_before_any_work(tmp_path):
    res = runner.invoke(app, ["benchmark", "--profile", "demo", "--device", "cuda", "--cache", str(tmp_path / "c"),
                              "--out", str(tmp_path / "o"), "--quiet"])
    assert res.exit_code == 2
    assert "device: 'cuda' requested but torch" in res.output and "sees no CUDA device" in res.output
    assert not (tmp_path / "c").exists()          # nothing simulated


def test_cpu_training_is_saved_and_loaded_as_cpu(dataset_dir, tmp_path):
    from quadformer.detectors import load

    cache = tmp_path / "cache"
    _fill(cache, Profile("one", 6, grid=PAPER_GRID[:1]), dataset_dir)
    name, cfg = profile_configs(Profile("one", 6, grid=PAPER_GRID[:1]))[0]
    path = cache / f"{name}-{dataset_key(cfg)}"
    model_dir = model_dir_for(cache, path, 0, 1.0)
    assert tune_unit(path, "cnn", 0, 1.0, 1.0, model_dir, "cpu", budget=BUDGET)["cached"] is False
    doc = json.loads(next(p for p in model_dir.glob("cnn-*.json") if ".tuned." not in p.name).read_text())
    assert doc["params"]["device"] == "cpu"
    det = cached_model("cnn", 1.0, model_dir, BUDGET).detector
    assert all(p.device.type == "cpu" for p in det.model_.parameters())


@pytest.mark.parametrize("args, message", [
    (["--backend", "dask"], "backend: unknown choice 'dask'; choose from local, ray"),
    (["--address", "auto"], "address: only with the ray backend"),
    (["--backend", "ray", "--address", "somewhere"], "address: expected auto, ray://host:port or host:port"),
    (["--device", "tpu"], "device: unknown choice 'tpu'"),
])
def test_backend_and_device_errors(args, message, tmp_path):
    for command in ("benchmark", "resilience"):
        res = runner.invoke(app, [command, "--cache", str(tmp_path / "c"), "--out", str(tmp_path / "o"), *args])
        assert res.exit_code == 2, res.output
        assert message in res.output
    assert not (tmp_path / "c").exists()


def test_ray_backend_without_ray_says_how_to_install_it(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)      # as if Ray were not installed
    res = runner.invoke(app, ["benchmark", "--backend", "ray", "--cache", str(tmp_path / "c"),
                              "--out", str(tmp_path / "o")])
    assert res.exit_code == 2
    assert "the ray backend needs Ray, which is not installed: pip install 'quadformer[ray]'" in res.output


def test_a_lock_left_by_a_dead_process_is_taken_over_and_a_live_one_is_waited_for(tmp_path):
    import socket
    import subprocess

    from quadformer.io import LockTimeout, exclusive

    entry = tmp_path / "entry"
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True,
                          check=True)
    (tmp_path / "entry.lock").write_text(f"{socket.gethostname()} {int(dead.stdout)}\n")   # killed mid-write
    with exclusive(entry, timeout_s=5) as lock:
        assert lock.read_text().split() == [socket.gethostname(), str(os.getpid())]
        with pytest.raises(LockTimeout, match="entry.lock: held by"):
            with exclusive(entry, poll_s=0.05, timeout_s=0.3):
                pass
    assert not (tmp_path / "entry.lock").exists()


def test_a_tuned_models_cache_key_covers_its_own_code_and_not_the_other_methods():
    """A change to the CUSUM must not retrain the networks, nor the reverse; every method's key
    covers the module defining it, what it imports from the detectors package and the residue
    schema (a plugin defined outside the package is covered by its own file)."""
    package = Path(quadformer.__file__).resolve().parent

    def names(method):      # paths inside the package relative to it (wherever the clone lies)
        return {p.resolve().relative_to(package).as_posix() if p.resolve().is_relative_to(package) else p.as_posix()
                for p in detector_sources(method)}

    cusum, cnn, quad, pca = names("cusum"), names("cnn"), names("quadformer"), names("pca")
    assert {"detectors/classical.py", "detectors/base.py", "estimator/schema.py"} <= cusum
    assert not any(n.startswith("detectors/neural/") for n in cusum) and "detectors/pca.py" not in cusum
    assert {"detectors/neural/detector.py", "detectors/neural/training.py", "detectors/windows.py",
            "detectors/context.py"} <= cnn and "detectors/classical.py" not in cnn
    assert {"detectors/neural/quadformer.py", "detectors/neural/quadformer_net.py",
            "detectors/neural/training.py"} <= quad and "detectors/classical.py" not in quad
    assert "detectors/neural/quadformer.py" not in cnn and "detectors/pca.py" in pca
    assert detectors_digest("cusum") == detectors_digest("bht") != detectors_digest("cnn") != detectors_digest("quadformer")

    class PluginCusum(Cusum):      # a user's detector, defined outside the package
        pass

    assert Path(__file__).resolve() in {p.resolve() for p in detector_sources(PluginCusum)}
    assert "detectors/classical.py" in names(PluginCusum)
