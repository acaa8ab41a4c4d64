"""The paper's eight configurations: Model I/II x exponential/laplace noise x bias/ramp."""

from __future__ import annotations

import itertools
import json
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from scipy import stats

from quadformer.config import SimConfig
from quadformer.simulation.dataset import Dataset, simulate, write_dataset

PAPER_GRID = tuple(itertools.product(("I", "II"), ("exponential", "laplace"), ("bias", "ramp")))


def config_name(model: str, noise: str, attack: str) -> str:
    return f"model{model}-{noise}-{attack}"


def noise_stats(ds: Dataset) -> dict[str, float]:
    """Moments of the GPS velocity noise (white, of the configured shape) on clean steps."""
    f = ds.flights[ds.flights["label"] == 0]
    err = (f[["gps_vel_x", "gps_vel_y", "gps_vel_z"]].to_numpy()
           - f[["true_vel_x", "true_vel_y", "true_vel_z"]].to_numpy()).reshape(-1)
    return {"std": float(err.std()), "skewness": float(stats.skew(err)),
            "excess_kurtosis": float(stats.kurtosis(err))}


def dataset_summary(ds: Dataset) -> dict[str, Any]:
    s = dict(ds.meta["summary"])
    s["attacked_fraction"] = s["attacked_flights"] / s["flights"]
    s["gps_vel_noise"] = noise_stats(ds)
    return s


def simulate_grid(base: SimConfig, out: Path | None = None, progress: bool = True,
                  overwrite: bool = False) -> list[dict[str, Any]]:
    """Simulate every paper configuration with ``base``'s other settings."""
    rows = []
    for model, noise, attack in PAPER_GRID:
        cfg = base.replace(model=model, noise=noise, attack=base.attack.__class__(
            **{**base.attack.__dict__, "kind": attack, "duration": None, "magnitude": None, "rate": None,
               "frequency": None, "period": None, "delay": None}))
        name = config_name(model, noise, attack)
        ds = simulate(cfg, progress=progress)
        if out is not None:
            write_dataset(ds, Path(out) / name, overwrite=overwrite)
        rows.append({"config": name, "model": model, "noise": noise, "attack": attack, **dataset_summary(ds)})
    if out is not None:
        (Path(out) / "summary.json").write_text(json.dumps(rows, indent=2))
    return rows


def summary_table(rows: list[dict[str, Any]]) -> pd.DataFrame:
    return pd.DataFrame([{
        "config": r["config"],
        "flights": r["flights"],
        "attacked": f"{r['attacked_fraction']:.2f}",
        "gps noise std": f"{r['gps_vel_noise']['std']:.3f}",
        "skew": f"{r['gps_vel_noise']['skewness']:.2f}",
        "ex.kurt": f"{r['gps_vel_noise']['excess_kurtosis']:.2f}",
        "NIS clean": _fmt(r["mean_nis_clean"]),
        "NIS attacked": _fmt(r["mean_nis_attacked"]),
        "max dev clean (m)": _fmt(r["max_deviation_clean_m"]),
        "max dev attacked (m)": _fmt(r["max_deviation_attacked_m"]),
    } for r in rows])


def _fmt(x: float | None) -> str:
    return "-" if x is None or not np.isfinite(x) else f"{x:.2f}"
