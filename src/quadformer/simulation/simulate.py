"""Simulated datasets: many flights of one configuration, in batches.

Flight i's data depends only on (config, seed, i): the batch size changes speed, not data.
The columns follow the sensor configuration (``estimator.schema.groups_for``).
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import pandas as pd

from quadformer.config import SimConfig
from quadformer.dataset import FORMAT_VERSION, Dataset, summarize
from quadformer.estimator.schema import groups_for
from quadformer.io import package_versions
from quadformer.rng import attacked_flights
from quadformer.simulation.closed_loop import BatchResult, simulate_batch


def _batch_frames(cfg: SimConfig, r: BatchResult) -> tuple[pd.DataFrame, pd.DataFrame]:
    B, n = r["label"].shape
    m, w, a = r["missions"], r["wind_params"], r["attacks"]
    kinds = np.asarray(a.kind, dtype=object)     # each flight's own kind ("none": not attacked)
    cols: dict[str, np.ndarray] = {
        "flight_id": np.repeat(r["flights"].astype(np.int32), n),
        "t": np.tile(r["t"], B),
        "label": r["label"].reshape(-1).astype(np.int8),
    }
    cols["attack_type"] = np.where(cols["label"] == 1, np.repeat(kinds, n), "none")
    for g in groups_for(cfg.sensors):      # the columns follow the sensor configuration
        for i, c in enumerate(g.columns):
            cols[c] = r[g.name][..., i].reshape(-1)
    flights = pd.DataFrame(cols)
    flights["attack_type"] = flights["attack_type"].astype("string")

    scen = pd.DataFrame({
        "flight_id": r["flights"].astype(np.int32),
        "mission": m.kind.astype(str), "speed": m.speed, "altitude": m.altitude,
        "wind_mean_x": w.mean[:, 0], "wind_mean_y": w.mean[:, 1], "gust_std": w.gust_std[:, 0],
        "attacked": a.attacked, "attack_type": np.where(a.attacked, kinds, "none").astype(str),
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
