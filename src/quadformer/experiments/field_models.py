"""Where the field benchmark's detectors come from: tuned on a simulation of the fleet's sensor
configuration with its noise (``tune_methods``, cached in the run's ``models/``), or a shipped
set's (``shipped_detectors``; ``detectors.pretrained``) with the checksums of the files judged."""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Any, Callable

from quadformer.config import SimConfig, unset_kind_fields
from quadformer.experiments.field_plan import FieldPlan
from quadformer.io import atomic_write_text


__all__ = ["tune_methods", "shipped_detectors", "shipped_files"]


def tune_methods(plan: FieldPlan, cfg: SimConfig, out: Path, echo: Callable[[str], None]) -> dict[str, Any]:
    """Each method tuned on the simulated dataset (cached in ``out/models``)."""
    from quadformer.detectors import load
    from quadformer.evaluation.protocol import split_flights, tune
    from quadformer.simulation import simulate

    models = out / "models"
    models.mkdir(parents=True, exist_ok=True)
    d = dataclasses.asdict(cfg)
    unset_kind_fields(d["attack"])          # a configuration's key as before drift and capture existed
    key = json.dumps(d, sort_keys=True, default=str) + f"|{plan.label_fraction}"
    stamp = models / "config.json"
    if not stamp.exists() or stamp.read_text() != key:
        for f in models.glob("*.qfm*"):
            f.unlink()
    trained, parts = {}, None
    for m in plan.methods:
        path = models / f"{m}.qfm"
        if path.exists():
            trained[m] = load(path)
            echo(f"  {m}: reused {path}")
            continue
        if parts is None:
            t0 = time.perf_counter()
            sim = simulate(cfg)
            parts = (split_flights(sim.scenarios, plan.seed, label_fraction=plan.label_fraction).frames(sim.flights),
                     sim.gps_rate_hz, sim.meta.get("config"))
            echo(f"  simulated {cfg.flights} training flights in {time.perf_counter() - t0:.0f} s")
        t0 = time.perf_counter()
        fr, rate, sim_config = parts
        det = tune(m, fr.train, fr.y_train, fr.val, gps_rate_hz=rate).detector
        det.calibrate(det.threshold_, det.budget_threshold_, split_seed=plan.seed, label_fraction=plan.label_fraction,
                      sim_config=sim_config)      # so that `detect` replays a log with this filter tuning
        trained[m] = det
        det.save(path)
        atomic_write_text(stamp, key)
        echo(f"  {m}: tuned in {time.perf_counter() - t0:.0f} s")
    return trained


def shipped_detectors(name: str) -> tuple[dict[str, Any], dict[str, Any]]:
    """(method -> detector at its validation-F1 threshold, the simulation they learned from) of
    the shipped set ``name``, which must read the project's filter's (``ekf``) residues."""
    from quadformer.detectors import pretrained

    sets = pretrained.sets()
    if name not in sets or sets[name].residues != "ekf":
        raise ValueError(f"shipped: {name!r} is not a shipped set of ekf residues; choose from "
                         f"{', '.join(k for k, v in sets.items() if v.residues == 'ekf')}")
    dets = {e.method: pretrained.load(e.name, threshold="f1") for e in pretrained.entries().values()
            if e.set.name == name}
    return dets, next(iter(dets.values())).calibration_["sim_config"]


def shipped_files(name: str) -> dict[str, dict[str, str]]:
    """The files and SHA-256 of a shipped set's detectors (what a field run judged)."""
    from quadformer.detectors import pretrained

    return {e.name: dict(e.files) for e in pretrained.entries().values() if e.set.name == name}
