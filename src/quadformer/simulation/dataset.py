"""Datasets: simulate many flights in batches and write them atomically.

A dataset directory holds
- ``flights.parquet``: one row per GPS step (see ``FLIGHT_COLUMNS`` and the ``res_*`` residues);
- ``scenarios.parquet``: one row per flight (mission, wind, attack parameters);
- ``meta.json``: the resolved config, seed, package versions and a summary.
"""

from __future__ import annotations

import json
import os
import platform
import shutil
import tempfile
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pandas as pd
import torch

from quadformer.config import SimConfig
from quadformer.rng import attacked_flights
from quadformer.simulation.closed_loop import RECORDS, BatchResult, column_names, simulate_batch

FORMAT_VERSION = 2   # 2: res_gps_corr_* added
# Column groups of flights.parquet after flight_id, t, label, attack_type.
COLUMN_ORDER = ("true_pos", "true_vel", "ref_pos", "est_pos", "est_vel", "gps_pos", "gps_vel", "vio_pos",
                "atk_d", "wind", *[k for k in RECORDS if k.startswith("res_")])
PACKAGES = ("quadformer", "numpy", "torch", "rotorpy", "pandas", "pyarrow", "roma", "scipy")


@dataclass
class Dataset:
    flights: pd.DataFrame     # one row per GPS step
    scenarios: pd.DataFrame   # one row per flight
    meta: dict[str, Any]

    @property
    def config(self) -> SimConfig:
        return SimConfig.from_dict(self.meta["config"])

    @property
    def residue_columns(self) -> list[str]:
        return [c for c in self.flights.columns if c.startswith("res_")]


def package_versions() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for name in PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


def _batch_frames(cfg: SimConfig, r: BatchResult) -> tuple[pd.DataFrame, pd.DataFrame]:
    B, n = r["label"].shape
    kind = cfg.attack.kind
    cols: dict[str, np.ndarray] = {
        "flight_id": np.repeat(r["flights"].astype(np.int32), n),
        "t": np.tile(r["t"], B),
        "label": r["label"].reshape(-1).astype(np.int8),
    }
    cols["attack_type"] = np.where(cols["label"] == 1, kind, "none")
    arrays = {**{k: v for k, v in r.items() if k in RECORDS}, "ref_pos": r["ref_pos"]}
    for name in COLUMN_ORDER:
        names = column_names(name) if name in RECORDS else [f"{name}_{a}" for a in "xyz"]
        for i, c in enumerate(names):
            cols[c] = arrays[name][..., i].reshape(-1)
    flights = pd.DataFrame(cols)
    flights["attack_type"] = flights["attack_type"].astype("string")

    m, w, a = r["missions"], r["wind_params"], r["attacks"]
    scen = pd.DataFrame({
        "flight_id": r["flights"].astype(np.int32),
        "mission": m.kind.astype(str), "speed": m.speed, "altitude": m.altitude,
        "wind_mean_x": w.mean[:, 0], "wind_mean_y": w.mean[:, 1], "gust_std": w.gust_std[:, 0],
        "attacked": a.attacked, "attack_type": np.where(a.attacked, kind, "none"),
        "attack_axes": a.axes.astype(str), "onset": a.onset, "end": a.end,
        "magnitude": a.magnitude, "rate": a.rate, "frequency": a.frequency, "period": a.period,
        "delay": a.delay,
        "dir_x": a.direction[:, 0], "dir_y": a.direction[:, 1], "dir_z": a.direction[:, 2],
    })
    return flights, scen


def simulate(cfg: SimConfig, progress: bool | Callable[[float], None] = False) -> Dataset:
    """Simulate ``cfg.flights`` flights in batches of ``cfg.batch_size``.

    Flight i's data depends only on (config, seed, i): the batch size changes speed, not data.
    """
    attacked = attacked_flights(cfg.seed, cfg.flights, cfg.attack.fraction if cfg.attack.kind != "none" else 0.0)
    bar = None
    if progress is True:
        from tqdm.auto import tqdm
        bar = tqdm(total=cfg.flights * int(cfg.duration), unit="flight-s", desc="simulate", mininterval=1.0)
        callback = bar.update
    else:
        callback = progress or None
    frames, scens = [], []
    try:
        for start in range(0, cfg.flights, cfg.batch_size):
            ids = np.arange(start, min(start + cfg.batch_size, cfg.flights))
            r = simulate_batch(cfg, ids, attacked[ids], progress=callback)
            f, s = _batch_frames(cfg, r)
            frames.append(f)
            scens.append(s)
    finally:
        if bar is not None:
            bar.close()
    flights = pd.concat(frames, ignore_index=True)
    scenarios = pd.concat(scens, ignore_index=True)
    meta = {
        "format_version": FORMAT_VERSION,
        "config": cfg.to_dict(),
        "seed": cfg.seed,
        "versions": package_versions(),
        "summary": summarize(flights, scenarios),
    }
    return Dataset(flights, scenarios, meta)


def summarize(flights: pd.DataFrame, scenarios: pd.DataFrame) -> dict[str, Any]:
    lab = flights["label"].to_numpy() == 1
    nis = flights["res_gps_nis"].to_numpy()
    dev = np.linalg.norm(flights[["true_pos_x", "true_pos_y", "true_pos_z"]].to_numpy()
                         - flights[["ref_pos_x", "ref_pos_y", "ref_pos_z"]].to_numpy(), axis=1)
    return {
        "flights": int(len(scenarios)),
        "attacked_flights": int(scenarios["attacked"].sum()),
        "rows": int(len(flights)),
        "attacked_rows": int(lab.sum()),
        "mean_nis_clean": float(nis[~lab].mean()) if (~lab).any() else None,
        "mean_nis_attacked": float(nis[lab].mean()) if lab.any() else None,
        "max_deviation_clean_m": float(dev[~lab].max()) if (~lab).any() else None,
        "max_deviation_attacked_m": float(dev[lab].max()) if lab.any() else None,
    }


def write_dataset(ds: Dataset, out: str | os.PathLike, overwrite: bool = False) -> Path:
    """Write a dataset directory atomically: into a temporary sibling, then renamed."""
    out = Path(out)
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out} already exists (pass overwrite=True / --overwrite to replace it)")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    try:
        ds.flights.to_parquet(tmp / "flights.parquet", index=False)
        ds.scenarios.to_parquet(tmp / "scenarios.parquet", index=False)
        (tmp / "meta.json").write_text(json.dumps(ds.meta, indent=2, default=_json_default))
        if out.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".old", dir=out.parent))
            os.replace(out, old / out.name)
            os.replace(tmp, out)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


def _json_default(o: Any) -> Any:
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o)}")


class DatasetError(ValueError):
    """A dataset directory that is missing, incomplete or corrupt."""


REQUIRED = ("flight_id", "t", "label", "attack_type", "res_gps_nis")


def load_dataset(path: str | os.PathLike) -> Dataset:
    path = Path(path)
    if not path.is_dir():
        raise DatasetError(f"{path}: no such dataset directory")
    try:
        meta = json.loads((path / "meta.json").read_text())
    except FileNotFoundError:
        raise DatasetError(f"{path}: meta.json is missing") from None
    except json.JSONDecodeError as e:
        raise DatasetError(f"{path / 'meta.json'}: not valid JSON ({e})") from None
    try:
        flights = pd.read_parquet(path / "flights.parquet")
        scenarios = pd.read_parquet(path / "scenarios.parquet")
    except FileNotFoundError as e:
        raise DatasetError(f"{path}: {Path(e.filename).name if e.filename else 'a parquet file'} is missing") from None
    except Exception as e:  # pyarrow raises several types on corrupt or truncated files
        raise DatasetError(f"{path}: cannot read parquet ({type(e).__name__}: {e})") from None
    missing = [c for c in REQUIRED if c not in flights.columns]
    if missing:
        raise DatasetError(f"{path / 'flights.parquet'}: missing columns {', '.join(missing)}")
    return Dataset(flights, scenarios, meta)


def set_threads(n: int | None = None) -> None:
    """Torch intra-op threads for the simulation (default: all cores)."""
    torch.set_num_threads(n or os.cpu_count() or 1)
