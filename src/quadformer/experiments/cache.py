"""Caches shared by the experiments: simulated datasets and tuned detectors.

- Datasets are keyed by their full configuration (a hash of the resolved ``SimConfig``
  without the batch size, plus the dataset format version): ``CACHE/<config>-<key>/``.
- Tuned detectors are keyed by dataset, split seed and label fraction (one directory), then
  method, false-alarm budget and a hash of the detector code:
  ``CACHE/models/<dataset>-s<seed>-l<fraction>/<method>-b<budget>-<code>[-t<training budget>].{json,pt,tuned.json}``
  (a reduced training budget, ``protocol.TrainingBudget``, has its own entries).
  The detection and resilience benchmarks share them instead of training twice; a change
  of a method's code invalidates its entries: the hash covers the module that defines the
  method, the modules of ``quadformer.detectors`` it imports (transitively) and the residue
  schema, so a change to the CUSUM leaves the networks' tuned models valid, and the reverse.

Several workers, of one run or of several runs sharing a cache directory (``--cache`` on
shared storage), may ask for the same entry at once:

- a run dispatches each entry once (units are deduplicated before dispatch);
- a worker builds an entry only while holding its lock file (``<entry>.lock``, created with
  ``O_CREAT | O_EXCL``, see ``io.exclusive``), and looks again once it holds it: a worker that
  waited on another's lock reads the entry that one wrote instead of building it twice;
- every entry is published atomically (written beside, then renamed into place; a tuned
  model's ``.tuned.json`` last), so a half-written entry is never read; an unreadable entry
  is rebuilt.
"""

from __future__ import annotations

import ast
import contextlib
import functools
import hashlib
import importlib.util
import inspect
import json
import os
import time
from pathlib import Path
from typing import Any

import pandas as pd

from quadformer.config import MIX, SimConfig, unset_kind_fields
from quadformer.dataset import FORMAT_VERSION, DatasetError, load_dataset, write_dataset
from quadformer.evaluation.protocol import TrainingBudget, Tuned, tune
from quadformer.experiments.grid import Profile, dataset_summary, profile_configs
from quadformer.experiments.pool import Backend, cluster_gpus, run_jobs
from quadformer.io import exclusive, write_json


# settings that change nothing unless the sensor is configured (SimConfig field, EKFConfig fields)
_SENSOR_SETTINGS = {"mag": ("mag", ("mag_heading_std_deg",)), "baro": ("baro", ("baro_std",))}


def dataset_key(cfg: SimConfig) -> str:
    d = cfg.to_dict()
    d.pop("batch_size", None)   # does not change the data
    # neither do the settings of sensors the configuration leaves out; so the default
    # configuration keeps the key it had before sensor configurations existed
    for sensor, (name, ekf_fields) in _SENSOR_SETTINGS.items():
        if not cfg.has(sensor):
            d.pop(name)
            for f in ekf_fields:
                d["ekf"].pop(f)
    if cfg.sensors == SimConfig.sensors:
        d.pop("sensors")
    if cfg.attack.kind != MIX:
        d["attack"].pop("mix")   # the kinds of a mixed attack: nothing to a single kind
    unset_kind_fields(d["attack"])
    d["format_version"] = FORMAT_VERSION   # what the simulator writes
    if not cfg.has("vio"):
        # without a camera the GPS-free reference is reset every few seconds, and how a reset
        # enters res_ref_vmean's whitening changed (2), and what the resets' shifts leave out is
        # recorded for the shape typer (3: res_ref_reset); with a camera it is never reset, so
        # those datasets are the same (res_ref_reset is 0) and keep their keys
        d["reference_resets"] = 3
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


def simulate_dataset(cfg: SimConfig, out: Path, overwrite: bool = True) -> bool:
    """One work unit: simulate ``cfg`` and write it to ``out``, holding the entry's lock, unless
    a readable dataset is there once the lock is held (another worker wrote it). Returns
    whether this call simulated it."""
    from quadformer.simulation import simulate

    with exclusive(out):
        try:
            load_dataset(out)
            return False
        except DatasetError:
            pass
        ds = simulate(cfg, progress=False)
        write_dataset(ds, out, overwrite=overwrite)
    return True


def ensure_datasets(profile: Profile, cache_dir: Path, progress: bool = True,
                    workers: int | None = None, backend: Backend | None = None) -> dict[str, Path]:
    """Paths of the profile's datasets, simulating those not in the cache."""
    return ensure_configs(profile_configs(profile), cache_dir, progress=progress, workers=workers, backend=backend)


def ensure_configs(configs: list[tuple[str, SimConfig]], cache_dir: Path, progress: bool = True,
                   workers: int | None = None, backend: Backend | None = None) -> dict[str, Path]:
    """Paths of named datasets (``CACHE/<name>-<key>/``), simulating those not in the cache,
    each dataset once. The missing datasets' flights fly together: configurations that differ
    only in model, noise, attack and seed share batches (``simulation.simulate.plan_batches``),
    one work unit per batch and as many batches as workers, so the simulator's per-step cost
    is paid once per worker instead of once per dataset. Each dataset is written exactly as
    ``simulate`` of its configuration alone would write it, while this process holds its lock."""
    cache_dir = Path(cache_dir)
    paths, jobs, labels = {}, {}, {}
    for name, cfg in configs:
        path = cache_dir / f"{name}-{dataset_key(cfg)}"
        paths[name] = path
        if path in jobs:
            continue
        if not _readable(path):
            jobs[path] = cfg
            labels[path] = name
    if not jobs:
        return paths
    with contextlib.ExitStack() as locks:
        todo = []
        for path in sorted(jobs):          # one order for every run: no two runs wait on each other
            locks.enter_context(exclusive(path))
            if not _readable(path):        # another run may have written it while this one waited
                todo.append(path)
        simulate_into([(jobs[p], p) for p in todo], progress=progress, workers=workers, backend=backend,
                      names=[labels[p] for p in todo])
    return paths


def _readable(path: Path) -> bool:
    try:
        load_dataset(path)
        return True
    except DatasetError:
        return False


def batch_count(workers: int | None = None, backend: Backend | None = None) -> int:
    """How many batches to split a run's flights into: one per worker (default: one per core)."""
    return max(1, workers or os.cpu_count() or 1)


def simulate_into(entries: list[tuple[SimConfig, Path]], progress: bool = True, workers: int | None = None,
                  backend: Backend | None = None, names: list[str] | None = None) -> None:
    """Simulate the configurations of ``entries`` and write each dataset to its path (the caller
    holds the entries' locks): mixed batches, one work unit per batch, on ``backend``."""
    from quadformer.simulation.simulate import assemble, plan_batches

    if not entries:
        return
    cfgs = [c for c, _ in entries]
    names = names or [p.name for _, p in entries]
    plan = plan_batches(cfgs, batch_count(workers, backend))
    units = [([(cfgs[i], ids) for i, ids in batch],) for batch in plan]
    unit_labels = ["flights of " + ", ".join(f"{names[i]} ({len(ids)})" for i, ids in batch) for batch in plan]
    outputs = run_jobs(simulate_unit, units, workers=workers, progress=progress, desc="simulate", unit="batch",
                       backend=backend, labels=unit_labels)
    parts: dict[int, list] = {i: [] for i in range(len(cfgs))}
    for batch, frames in zip(plan, outputs):
        for (i, ids), fs in zip(batch, frames):
            parts[i].append((int(ids[0]), fs))
    for i, (cfg, path) in enumerate(entries):
        ds = assemble(cfg, [fs for _, fs in sorted(parts[i], key=lambda x: x[0])])
        write_dataset(ds, path, overwrite=True)


def simulate_unit(parts: list[tuple[SimConfig, Any]]) -> list:
    """One work unit: one mixed batch (``simulation.simulate.simulate_parts``); returns each
    part's (flights, scenarios) frames."""
    from quadformer.simulation.simulate import simulate_parts

    return simulate_parts(parts)


_PACKAGE = "quadformer.detectors"


def _module_file(name: str) -> Path | None:
    try:
        spec = importlib.util.find_spec(name)
    except (ImportError, ValueError):      # a name inside a module, not a module
        return None
    return Path(spec.origin) if spec is not None and spec.origin not in (None, "built-in", "frozen") else None


def _detector_imports(path: Path) -> set[str]:
    """Modules of ``quadformer.detectors`` the source file ``path`` imports (a name imported
    from a package counts as its submodule when it is one)."""
    ours = lambda m: m == _PACKAGE or m.startswith(_PACKAGE + ".")  # noqa: E731
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names if ours(a.name))
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0 and ours(node.module):
            package = (_module_file(node.module) or Path()).name == "__init__.py"
            subs = [m for m in (f"{node.module}.{a.name}" for a in node.names) if package and _module_file(m)]
            found.update(subs if subs else [node.module])
    return found


def detector_sources(method: str | type) -> list[Path]:
    """The source files a tuned model of ``method`` (a registered name or a detector class)
    depends on, sorted: the module that defines its class (a plugin's too) and those of its
    bases in this package, the modules of ``quadformer.detectors`` they import (transitively)
    and the residue schema."""
    from quadformer.detectors import get
    from quadformer.estimator import schema

    cls = get(method) if isinstance(method, str) else method
    todo = {cls.__module__} | {c.__module__ for c in inspect.getmro(cls) if c.__module__.startswith("quadformer")}
    files: dict[str, Path] = {}
    while todo:
        name = todo.pop()
        path = _module_file(name)
        if path is None:
            continue
        files[name] = path
        todo |= _detector_imports(path) - set(files)
    return sorted({*files.values(), Path(schema.__file__)})


@functools.lru_cache(maxsize=None)
def detectors_digest(method: str) -> str:
    """Hash of ``detector_sources(method)``: a tuned model cached by an older version of that
    code is not reused."""
    h = hashlib.sha256()
    for path in detector_sources(method):
        h.update(path.read_bytes())
    return h.hexdigest()[:12]


def model_dir_for(cache_dir: Path, dataset_path: Path, seed: int, label_fraction: float) -> Path:
    """Where tuned detectors of one dataset, split seed and label fraction are cached."""
    return Path(cache_dir) / "models" / f"{Path(dataset_path).name}-s{seed}-l{label_fraction:g}"


def tuned_model(method: str, train: pd.DataFrame, y_train, val: pd.DataFrame, rate: float,
                budget_per_hour: float, model_dir: Path | None, device: str | None = None,
                budget: TrainingBudget | None = None) -> Tuned:
    """``protocol.tune``, cached in ``model_dir`` (None: always tune). A miss is tuned while
    holding the entry's lock; a worker that waited on that lock reads what the holder wrote.

    device: where network detectors train (resolved, e.g. ``cpu`` or ``cuda``; None: their
    default); a model is saved and loaded the same whatever device it trained on.
    budget: a reduced training budget (None: the full one), part of the cache key."""
    if model_dir is None:
        return tune(method, train, y_train, val, gps_rate_hz=rate, budget_per_hour=budget_per_hour, device=device,
                    budget=budget)
    stem = model_stem(method, budget_per_hour, budget)
    model_path, meta_path = Path(model_dir) / f"{stem}.json", Path(model_dir) / f"{stem}.tuned.json"
    found = cached_model(method, budget_per_hour, model_dir, budget)
    if found is not None:
        return found
    with exclusive(model_path):
        found = cached_model(method, budget_per_hour, model_dir, budget)   # written while this worker waited
        if found is not None:
            return found
        tuned = tune(method, train, y_train, val, gps_rate_hz=rate, budget_per_hour=budget_per_hour, device=device,
                     budget=budget)
        tuned.detector.save(model_path)
        write_json(meta_path, {"params": tuned.params, "val_f1": tuned.val_f1, "grid": tuned.grid})   # published last
    return tuned


def model_stem(method: str, budget_per_hour: float, budget: TrainingBudget | None = None) -> str:
    """File name stem of a tuned model's cache entry: the method, the false-alarm budget, a
    digest of the detectors' code, and the reduced training budget if there is one (models
    trained on another budget never share an entry)."""
    stem = f"{method}-b{budget_per_hour:g}-{detectors_digest(method)}"
    return stem if budget is None else f"{stem}-t{budget.name}{budget.fraction:g}"


def cached_model(method: str, budget_per_hour: float, model_dir: Path,
                 budget: TrainingBudget | None = None) -> Tuned | None:
    """The tuned detector cached in ``model_dir``, or None when there is none (or it is
    unreadable: it will be tuned again and overwritten)."""
    from quadformer.detectors import load

    stem = model_stem(method, budget_per_hour, budget)
    model_path, meta_path = Path(model_dir) / f"{stem}.json", Path(model_dir) / f"{stem}.tuned.json"
    if not meta_path.exists():
        return None
    try:
        meta = json.loads(meta_path.read_text())
        return Tuned(load(model_path), meta["params"], meta["val_f1"], meta["grid"], cached=True)
    except (OSError, ValueError, KeyError):
        return None


def trains_network(method: str) -> bool:
    """Whether a method trains a network (has a torch ``device`` parameter)."""
    from quadformer.detectors import get

    return "device" in inspect.signature(get(method).__init__).parameters


def check_device(device: str, backend: Backend | None = None, workers: int | None = None) -> float:
    """Fail early on a device the backend cannot give; returns the GPUs a unit that trains a
    network asks the backend for (Ray only: its ``gpu_share`` when the cluster has GPUs and the
    device is not ``cpu``; 0 otherwise)."""
    from quadformer.detectors.neural import resolve_device

    backend = backend or Backend()
    if backend.kind != "ray":
        resolve_device(device)     # raises when cuda is asked for and absent
        return 0.0
    if device not in ("auto", "cpu") and not device.startswith("cuda"):
        resolve_device(device)     # the unknown-choice error
    if device == "cpu":
        return 0.0
    if cluster_gpus(backend, workers) == 0:
        if device != "auto":
            raise ValueError(f"device: {device!r} requested but the Ray cluster has no GPU; use --device cpu or auto")
        return 0.0
    return backend.gpu_share


def tune_unit(dataset_path: Path, method: str, seed: int, label_fraction: float, budget_per_hour: float,
              model_dir: Path, device: str = "cpu", budget: TrainingBudget | None = None) -> dict[str, Any]:
    """One work unit: the tuned detector of one dataset, split and method, in the cache
    (tuned now unless there already). ``device`` is resolved here, in the worker
    (``auto``: this worker's GPU if it has one). Returns {"cached", "seconds"}."""
    from quadformer.detectors.neural import resolve_device
    from quadformer.evaluation.protocol import split_flights

    t0 = time.perf_counter()
    if cached_model(method, budget_per_hour, model_dir, budget) is not None:
        return {"cached": True, "seconds": time.perf_counter() - t0}
    ds = load_dataset(dataset_path)
    parts = split_flights(ds.scenarios, seed, label_fraction=label_fraction).frames(ds.flights)
    dev = resolve_device(device) if trains_network(method) else None
    tuned = tuned_model(method, parts.train, parts.y_train, parts.val, ds.gps_rate_hz, budget_per_hour, model_dir,
                        device=dev, budget=budget)
    return {"cached": tuned.cached, "seconds": time.perf_counter() - t0}


def ensure_tuned(items: list[tuple[str, Path, Path]], methods: list[str], seed: int, label_fraction: float,
                 budget_per_hour: float = 1.0, device: str = "cpu", progress: bool = True,
                 workers: int | None = None, backend: Backend | None = None,
                 budget: TrainingBudget | None = None) -> dict[tuple[str, str], dict[str, Any]]:
    """Tuned detectors of every (configuration, method) in the model cache: one work unit per
    pair not there yet, on ``backend``. ``items``: (configuration name, dataset path, model
    directory). Returns {(name, method): {"cached": bool, "seconds": tuning time}}."""
    gpu = check_device(device, backend, workers)
    out: dict[tuple[str, str], dict[str, Any]] = {}
    units, keys, labels, gpus = [], [], [], []
    for name, path, model_dir in items:
        for m in methods:
            if (name, m) in out or (name, m) in keys:
                continue
            if cached_model(m, budget_per_hour, model_dir, budget) is not None:
                out[(name, m)] = {"cached": True, "seconds": None}
                continue
            units.append((path, m, seed, label_fraction, budget_per_hour, model_dir, device, budget))
            keys.append((name, m))
            labels.append(f"config {name}, seed {seed}, method {m}")
            gpus.append(gpu if trains_network(m) else 0.0)
    done = run_jobs(tune_unit, units, workers=workers, progress=progress, desc="tune", unit="model",
                    backend=backend, labels=labels, gpus=gpus)
    out.update(zip(keys, done))
    return out
