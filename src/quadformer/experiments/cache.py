"""Caches shared by the experiments: simulated datasets and tuned detectors.

- Datasets are keyed by their full configuration (a hash of the resolved ``SimConfig``
  without the batch size, plus the dataset format version): ``CACHE/<config>-<key>/``.
- Tuned detectors are keyed by dataset, split seed and label fraction (one directory), then
  method, false-alarm budget and a hash of the detector code:
  ``CACHE/models/<dataset>-s<seed>-l<fraction>/<method>-b<budget>-<code>.{json,pt,tuned.json}``.
  The detection and resilience benchmarks share them instead of training twice; a change
  of the detector code invalidates them.

Every entry is published atomically (written beside, then renamed), so a half-written entry
is never read; an unreadable entry is rebuilt.
"""

from __future__ import annotations

import functools
import hashlib
import json
from pathlib import Path
from typing import Any

import pandas as pd

from quadformer.config import MIX, SimConfig
from quadformer.dataset import FORMAT_VERSION, DatasetError, load_dataset, write_dataset
from quadformer.evaluation.protocol import Tuned, tune
from quadformer.experiments.grid import Profile, dataset_summary, profile_configs
from quadformer.experiments.pool import run_jobs
from quadformer.io import write_json


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
    d["format_version"] = FORMAT_VERSION   # what the simulator writes
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


def simulate_dataset(cfg: SimConfig, out: Path, overwrite: bool = True) -> dict[str, Any]:
    """One work unit: simulate ``cfg``, write it to ``out``; returns its summary."""
    from quadformer.simulation import simulate

    ds = simulate(cfg, progress=False)
    write_dataset(ds, out, overwrite=overwrite)
    return dataset_summary(ds)


def ensure_datasets(profile: Profile, cache_dir: Path, progress: bool = True,
                    workers: int | None = None) -> dict[str, Path]:
    """Paths of the profile's datasets, simulating those not in the cache."""
    return ensure_configs(profile_configs(profile), cache_dir, progress=progress, workers=workers)


def ensure_configs(configs: list[tuple[str, SimConfig]], cache_dir: Path, progress: bool = True,
                   workers: int | None = None) -> dict[str, Path]:
    """Paths of named datasets (``CACHE/<name>-<key>/``), simulating those not in the cache
    (in worker processes, one dataset per unit)."""
    cache_dir = Path(cache_dir)
    paths, jobs = {}, []
    for name, cfg in configs:
        path = cache_dir / f"{name}-{dataset_key(cfg)}"
        paths[name] = path
        try:
            load_dataset(path)
        except DatasetError:
            jobs.append((cfg, path))
    run_jobs(simulate_dataset, jobs, workers=workers, progress=progress, desc="simulate", unit="dataset")
    return paths


@functools.lru_cache(maxsize=1)
def detectors_digest() -> str:
    """Hash of the detector code and the residue schema: a tuned model cached by an older
    version is not reused."""
    import quadformer.detectors as pkg
    from quadformer.estimator import schema

    h = hashlib.sha256()
    for f in sorted(Path(pkg.__file__).parent.rglob("*.py")) + [Path(schema.__file__)]:
        h.update(f.read_bytes())
    return h.hexdigest()[:12]


def model_dir_for(cache_dir: Path, dataset_path: Path, seed: int, label_fraction: float) -> Path:
    """Where tuned detectors of one dataset, split seed and label fraction are cached."""
    return Path(cache_dir) / "models" / f"{Path(dataset_path).name}-s{seed}-l{label_fraction:g}"


def tuned_model(method: str, train: pd.DataFrame, y_train, val: pd.DataFrame, rate: float,
                budget_per_hour: float, model_dir: Path | None) -> Tuned:
    """``protocol.tune``, cached in ``model_dir`` (None: always tune)."""
    if model_dir is None:
        return tune(method, train, y_train, val, gps_rate_hz=rate, budget_per_hour=budget_per_hour)
    from quadformer.detectors import load

    stem = f"{method}-b{budget_per_hour:g}-{detectors_digest()}"
    model_path, meta_path = Path(model_dir) / f"{stem}.json", Path(model_dir) / f"{stem}.tuned.json"
    if meta_path.exists():
        try:
            meta = json.loads(meta_path.read_text())
            return Tuned(load(model_path), meta["params"], meta["val_f1"], meta["grid"], cached=True)
        except (OSError, ValueError, KeyError):
            pass   # unreadable cache entry: tune again and overwrite it
    tuned = tune(method, train, y_train, val, gps_rate_hz=rate, budget_per_hour=budget_per_hour)
    tuned.detector.save(model_path)
    write_json(meta_path, {"params": tuned.params, "val_f1": tuned.val_f1, "grid": tuned.grid})   # published last
    return tuned
