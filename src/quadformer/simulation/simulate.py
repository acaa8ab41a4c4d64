"""Simulated datasets: many flights of one configuration, in batches.

Flight i's data depends only on (config, seed, i): the batch size changes speed, not data.
The columns follow the sensor configuration (``estimator.schema.groups_for``).
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np
import pandas as pd

from quadformer.attacks import CAPTURE_RECEIVER
from quadformer.config import STEALTH, SimConfig
from quadformer.dataset import FORMAT_VERSION, Dataset, summarize
from quadformer.estimator.schema import groups_for
from quadformer.io import package_versions
from quadformer.rng import attacked_flights
from quadformer.simulation.closed_loop import BatchResult, mixable_families, simulate_batch, simulate_groups


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
    # the parameters of drift and capture, only where the configuration may draw them (the
    # scenarios of every other configuration keep their columns)
    drawn = set(cfg.attack.kinds)
    if STEALTH in drawn:              # its top speed is ``rate``; the black box's acceleration
        scen["accel"] = a.accel
    if "drift" in drawn:
        scen["accel"] = a.accel
        scen["onset_step"] = a.onset_step
    if "capture" in drawn:
        for name in ("capture_s", "lock_loss_s", *CAPTURE_RECEIVER):
            scen[name] = getattr(a, name)
    return flights, scen


def _attacked(cfg: SimConfig) -> np.ndarray:
    return attacked_flights(cfg.seed, cfg.flights, cfg.attack.fraction if cfg.attack.kind != "none" else 0.0)


def _dataset(cfg: SimConfig, frames: list[pd.DataFrame], scens: list[pd.DataFrame]) -> Dataset:
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


def simulate(cfg: SimConfig, progress: bool | Callable[[float], None] = False,
             on_batch: Callable[[BatchResult], None] | None = None, defence=None) -> Dataset:
    """Simulate ``cfg.flights`` flights in batches of ``cfg.batch_size``.

    Flight i's data depends only on (config, seed, i): the batch size changes speed, not data.
    on_batch: called with each batch's ``BatchResult``, its raw sensor streams recorded
    (``record_sensors``), before the next batch flies (e.g. to write each flight as a log);
    the dataset is the same with or without it.
    defence: a calibrated detector whose online alarms drive the ``resilient`` GPS policy in the
    loop (``resilience.Admission``, its default configuration): on an alarm GPS leaves the fusion
    and comes back once trustworthy again. The flights then also hold ``gps_fused`` (1 where the
    step's fix was fused) and ``alarm`` (the detector's alarm at the step, online).
    """
    attacked = _attacked(cfg)
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
            admission = stream = None
            if defence is not None:
                from quadformer.resilience import Admission

                admission = Admission(np.full(len(ids), "resilient", dtype=object), cfg.gps.rate_hz)
                stream = defence.stream(len(ids))
            r = simulate_batch(cfg, ids, attacked[ids], progress=callback, record_sensors=on_batch is not None,
                               admission=admission, stream=stream)
            if on_batch is not None:
                on_batch(r)
            f, s = _batch_frames(cfg, r)
            if defence is not None:
                f["gps_fused"] = r["admission"]["fused"].reshape(-1).astype(np.int8)
                f["alarm"] = r["admission"]["alarm"].reshape(-1).astype(np.int8)
            frames.append(f)
            scens.append(s)
    finally:
        if bar is not None:
            bar.close()
    return _dataset(cfg, frames, scens)


def plan_batches(cfgs: Sequence[SimConfig], n_batches: int = 1, batch_size: int | None = None,
                 ) -> list[list[tuple[int, np.ndarray]]]:
    """Split the flights of several configurations into batches that mix configurations:
    each batch a list of (configuration index, flight indices), configurations ``mixable``
    within a batch. Flights are dealt in order into at least ``n_batches`` batches (as even as
    possible) of at most ``batch_size`` flights (default: the first configuration's)."""
    cfgs = list(cfgs)
    out = []
    for fam in mixable_families(cfgs):
        units = [(i, f) for i in fam for f in range(cfgs[i].flights)]
        cap = batch_size or cfgs[fam[0]].batch_size
        n = max(n_batches, -(-len(units) // cap))
        for chunk in np.array_split(np.arange(len(units)), min(n, len(units))):
            batch: dict[int, list[int]] = {}
            for u in chunk:
                i, f = units[u]
                batch.setdefault(i, []).append(f)
            out.append([(i, np.asarray(fl)) for i, fl in batch.items()])
    return out


def simulate_parts(parts: Sequence[tuple[SimConfig, np.ndarray]],
                   progress: Callable[[float], None] | None = None) -> list[tuple[pd.DataFrame, pd.DataFrame]]:
    """One batch of flights of several (mixable) configurations: (config, flight indices) per
    part. Returns each part's (flights, scenarios) frames, exactly those ``simulate`` writes
    for these flights."""
    groups = [(cfg, ids, _attacked(cfg)[ids]) for cfg, ids in parts]
    results = simulate_groups(groups, progress=progress)
    return [_batch_frames(cfg, r) for (cfg, _), r in zip(parts, results)]


def simulate_many(cfgs: Sequence[SimConfig], progress: bool | Callable[[float], None] = False,
                  batch_size: int | None = None) -> list[Dataset]:
    """The datasets of several configurations, their flights mixed in as few batches as
    ``batch_size`` allows (default: the first configuration's): each dataset equals
    ``simulate(cfg)`` of its configuration, bit for bit. Configurations that differ in more
    than model, noise, attack, seed and size fly in batches of their own."""
    cfgs = list(cfgs)
    bar = None
    if progress is True:
        from tqdm.auto import tqdm
        bar = tqdm(total=sum(c.flights * int(c.duration) for c in cfgs), unit="flight-s", desc="simulate",
                   mininterval=1.0)
        callback = bar.update
    else:
        callback = progress or None
    frames: dict[int, list] = {i: [] for i in range(len(cfgs))}
    try:
        for batch in plan_batches(cfgs, 1, batch_size):
            for (i, ids), fs in zip(batch, simulate_parts([(cfgs[i], ids) for i, ids in batch], callback)):
                frames[i].append((int(ids[0]), fs))
    finally:
        if bar is not None:
            bar.close()
    return [assemble(c, [fs for _, fs in sorted(frames[i], key=lambda x: x[0])]) for i, c in enumerate(cfgs)]


def assemble(cfg: SimConfig, parts: Sequence[tuple[pd.DataFrame, pd.DataFrame]]) -> Dataset:
    """The dataset of ``cfg`` from the frames of its flights (``simulate_parts``), in flight order."""
    return _dataset(cfg, [f for f, _ in parts], [s for _, s in parts])
