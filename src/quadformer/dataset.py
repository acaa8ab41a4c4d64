"""Datasets: flights of any source in one on-disk format, written atomically.

A dataset directory holds
- ``flights.parquet``: one row per GPS step, the columns of ``estimator.schema`` (keys and
  labels, states, residues) of the flights' sensor configuration;
- ``scenarios.parquet``: one row per flight (for simulated flights: mission, wind, attack
  parameters; at least ``flight_id`` and ``attacked``);
- ``meta.json``: the resolved config, seed, package versions and a summary.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import pandas as pd

from quadformer.config import SimConfig
from quadformer.estimator.schema import RESIDUES, STATES
from quadformer.io import atomic_dir, to_json

FORMAT_VERSION = 3   # 2: res_gps_corr_* added; 3: the persistent residues (estimator/reference.py) added
# Column groups of flights.parquet after the keys (flight_id, t, label, attack_type), in
# order; a dataset holds those of its sensor configuration (``schema.groups_for``).
COLUMN_ORDER = tuple(g.name for g in STATES + RESIDUES)


@dataclass
class Dataset:
    flights: pd.DataFrame     # one row per GPS step
    scenarios: pd.DataFrame   # one row per flight
    meta: dict[str, Any]

    @property
    def config(self) -> SimConfig:
        """The simulation config of a simulated dataset."""
        if "config" not in self.meta:
            raise DatasetError(f"a dataset from {self.meta.get('source', 'an unknown source')} has no simulation "
                               "config")
        return SimConfig.from_dict(self.meta["config"])

    @property
    def gps_rate_hz(self) -> float:
        """GPS steps per second (the rows' rate)."""
        if "gps_rate_hz" in self.meta:
            return float(self.meta["gps_rate_hz"])
        return self.config.gps.rate_hz

    @property
    def residue_columns(self) -> list[str]:
        return [c for c in self.flights.columns if c.startswith("res_")]


def summarize(flights: pd.DataFrame, scenarios: pd.DataFrame) -> dict[str, Any]:
    lab = flights["label"].to_numpy() == 1
    nis = flights["res_gps_nis"].to_numpy() if "res_gps_nis" in flights.columns else np.full(len(flights), np.nan)
    cols = ["true_pos_x", "true_pos_y", "true_pos_z", "ref_pos_x", "ref_pos_y", "ref_pos_z"]
    dev = np.linalg.norm(flights[cols[:3]].to_numpy() - flights[cols[3:]].to_numpy(), axis=1) \
        if set(cols) <= set(flights.columns) else np.full(len(flights), np.nan)
    return {
        "flights": int(len(scenarios)),
        "attacked_flights": int(scenarios["attacked"].sum()),
        "rows": int(len(flights)),
        "attacked_rows": int(lab.sum()),
        "mean_nis_clean": _finite(np.mean, nis[~lab]),
        "mean_nis_attacked": _finite(np.mean, nis[lab]),
        "max_deviation_clean_m": _finite(np.max, dev[~lab]),
        "max_deviation_attacked_m": _finite(np.max, dev[lab]),
    }


def _finite(fn, x: np.ndarray) -> float | None:
    """fn of the values, None when there are none (or the column is absent: NaN)."""
    return float(fn(x)) if len(x) and np.isfinite(x).all() else None


def write_dataset(ds: Dataset, out: str | os.PathLike, overwrite: bool = False,
                  extra: Mapping[str, str | os.PathLike] | None = None) -> Path:
    """Write a dataset directory atomically: into a temporary sibling, then renamed.
    extra: {name: path} files or directories moved into it under those names before the
    rename (e.g. the flight logs of ``simulate --export``), on the same file system."""
    out = Path(out)
    with atomic_dir(out, overwrite=overwrite) as tmp:
        ds.flights.to_parquet(tmp / "flights.parquet", index=False)
        ds.scenarios.to_parquet(tmp / "scenarios.parquet", index=False)
        (tmp / "meta.json").write_text(to_json(ds.meta))
        for name, src in (extra or {}).items():
            os.replace(src, tmp / name)
    return out


class DatasetError(ValueError):
    """A dataset directory that is missing, incomplete or corrupt."""


REQUIRED = ("flight_id", "t", "label", "attack_type")


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
