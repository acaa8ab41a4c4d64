"""The shipped detectors' build (``quadformer zoo build``), from their recipes.

A recipe per sensor set (``RECIPES``, ``experiments.zoo_recipes``): the simulated flights its detectors learn from
(configurations, flights per configuration, seed) and the methods; the set's default is chosen
on the validation flights (``build``). The build simulates each set's flights (cached like the
benchmark's datasets), splits every configuration's flights by flight with the benchmark's
protocol (60/20/20, split seed 0, 20% of the training flights labelled), tunes each method on
the pooled training flights at its full training budget, calibrates it on the pooled validation
flights (the threshold of best F1 and the one meeting ``BUDGET_PER_HOUR`` false alarms per clean
flight-hour), scores the pooled test flights at both, and writes the saved detectors, their
SHA-256 and their cards into a fresh directory that replaces the old one only once everything is
written (``detectors.pretrained`` reads it).

Seeds. The zoo's flights derive from ``ZOO_SEED``; the benchmark's profiles from seed 0 (and
``--seed-list``'s small integers) and the demo's test flights from ``DEMO_SEED``: no flight a
benchmark or the demo tests on is one a shipped detector trained or was calibrated on.

Same machine, same seed, same files: the simulation and the tuning draw from explicit
generators, network training runs on ``THREADS`` CPU threads, and nothing in a saved file
depends on where or when it was built (the cards, in ``index.json``, hold the package
versions and the tuning times; the checksums cover the detector files only).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pandas as pd

from quadformer.config import SimConfig
from quadformer.dataset import load_dataset
from quadformer.detectors import pretrained
from quadformer.evaluation.metrics import bootstrap_f1, evaluate
from quadformer.evaluation.protocol import Tuned, split_flights, tune
from quadformer.experiments.cache import ensure_configs
from quadformer.experiments.provenance import provenance
from quadformer.experiments.zoo_recipes import FLEET_NOISE, PAPER_PROFILE_F1, RECIPES, Recipe
from quadformer.io import atomic_dir, package_versions, write_json

__all__ = ["ZOO_SEED", "DEMO_SEED", "THREADS", "BUDGET_PER_HOUR", "FLEET_NOISE", "PAPER_PROFILE_F1", "Recipe",
           "RECIPES", "build", "attach_field", "field_figures", "pooled_splits", "shipped_tuned"]

ZOO_SEED = 1000
DEMO_SEED = 2000
#: CPU threads the networks train on (fixed: float sums in another order give other weights)
THREADS = 2
BUDGET_PER_HOUR = 1.0
SPLIT_SEED = 0
LABEL_FRACTION = 0.2
#: offset between the flight ids of pooled configurations (a configuration has fewer flights)
ID_STRIDE = 1_000_000

def shipped_tuned(name: str, threshold: str = "f1") -> Tuned:
    """A shipped detector as the protocol's ``Tuned`` (its card's parameters and validation F1;
    ``cached``: nothing was tuned here), alarming at its ``threshold``."""
    e = pretrained.resolve(name)
    det = pretrained.load(e.name, threshold=threshold)
    tr = e.card["training"]
    return Tuned(det, dict(tr["params"]), float(tr["validation_f1"]), cached=True)


def pooled_splits(paths: dict[str, Path]) -> tuple[dict[str, pd.DataFrame], np.ndarray, dict[str, int],
                                                  dict[str, Any]]:
    """The train / validation / test flights of every configuration (split by flight, each
    configuration on its own), pooled with distinct flight ids; the training labels; the split's
    counts; and the first configuration's simulation (the filter tuning the residues came from)."""
    parts: dict[str, list[pd.DataFrame]] = {"train": [], "val": [], "test": []}
    labels, counts, sim = [], {"train": 0, "val": 0, "test": 0, "labelled": 0}, None
    for i, (name, path) in enumerate(paths.items()):
        ds = load_dataset(path)
        sim = sim or ds.meta.get("config")
        sp = split_flights(ds.scenarios, SPLIT_SEED, label_fraction=LABEL_FRACTION)
        fr = sp.frames(ds.flights)
        for k in parts:
            f = getattr(fr, k).copy()
            f["flight_id"] = f["flight_id"] + i * ID_STRIDE
            parts[k].append(f.assign(config=name))
            counts[k] += len(getattr(sp, k))
        counts["labelled"] += len(sp.labelled)
        labels.append(fr.y_train)
    return {k: pd.concat(v, ignore_index=True) for k, v in parts.items()}, np.concatenate(labels), counts, sim


def _figures(test: pd.DataFrame, scores: np.ndarray, threshold: float, rate: float) -> dict[str, Any]:
    """A card's figures of ``scores`` on flights ``test`` alarming above ``threshold``: pooled,
    with the F1's 95% bootstrap interval over flights, and the F1 of each configuration."""
    ids, y = test.flight_id.to_numpy(), test.label.to_numpy()
    alarms = scores > threshold
    offsets = np.linalg.norm(test[["atk_d_x", "atk_d_y", "atk_d_z"]].to_numpy(), axis=1)
    m = evaluate(ids, test.t.to_numpy(), y, scores, alarms, gps_rate_hz=rate, offsets=offsets, vus=False)
    ci = bootstrap_f1(ids, y, alarms, n_boot=1000, seed=0)
    keep = ("f1", "precision", "recall", "event_recall", "delay_median_s", "false_alarms_per_hour", "auroc")
    out = {k: m.get(k) for k in keep}
    out["f1_ci95"] = list(ci) if ci is not None else None
    out["threshold"] = float(threshold)
    out["per_config_f1"] = {}
    for name, g in test.groupby("config", sort=False):
        idx = g.index.to_numpy()
        out["per_config_f1"][name] = evaluate(ids[idx], g.t.to_numpy(), y[idx], scores[idx], alarms[idx],
                                              gps_rate_hz=rate, vus=False)["f1"]
    return out


def _simulation_doc(configs: list[tuple[str, SimConfig]]) -> list[dict[str, Any]]:
    out = []
    for name, c in configs:
        a = c.attack
        out.append({"config": name, "model": c.model, "noise": c.noise, "sensors": c.sensors, "flights": c.flights,
                    "duration_s": c.duration, "seed": c.seed, "attack": {"kind": a.kind, "mix": a.mix,
                                                                         "magnitude_m": a.magnitude,
                                                                         "rate_m_s": a.rate, "onset_s": a.onset,
                                                                         "fraction": a.fraction}})
    return out


def _rates(c: SimConfig) -> dict[str, float]:
    r = {"imu_hz": 1.0 / c.dt, "gps_hz": c.gps.rate_hz}
    for s in ("vio", "mag", "baro"):
        if s in c.sensors.split("+"):
            r[f"{s}_hz"] = getattr(c, s).rate_hz
    return r


def _kept(out: Path, rebuilt: set[str], methods: list[str] | None = None) -> dict[str, Any]:
    """What a partial build keeps of an existing zoo at ``out`` (its index entries; their files
    are copied over by the caller), none when there is no zoo: the sets it does not rebuild, and
    with ``methods`` the rebuilt sets' entries and their other methods' detectors too."""
    try:
        doc = pretrained.index(out)
    except pretrained.ZooError:
        return {"sets": {}, "detectors": {}}
    if methods:
        return {"sets": dict(doc["sets"]),
                "detectors": {k: v for k, v in doc["detectors"].items()
                              if v["set"] not in rebuilt or v["method"] not in methods}}
    return {"sets": {k: v for k, v in doc["sets"].items() if k not in rebuilt},
            "detectors": {k: v for k, v in doc["detectors"].items() if v["set"] not in rebuilt}}


def field_figures(results: dict[str, Any], method: str) -> dict[str, Any]:
    """A card's summary of a field run (``benchmark --profile field --shipped SET``) for ``method``:
    spoofing alerts in the air on the clean logs, and the injected spoofs' recall and delay, at
    each threshold."""
    keep_fa = ("threshold", "logs", "air_hours", "spoofing_air", "per_air_hour", "ci_low", "ci_high")
    keep_inj = ("threshold", "kind", "injected", "event_recall", "recall_big", "delay_median_s")
    return {"logs_read": len(results.get("read", [])), "logs_refused": len(results.get("refused", [])),
            "false_alarms_clean": [{k: r.get(k) for k in keep_fa} for r in results["false_alarms"]
                                   if r["method"] == method],
            "injected": [{k: r.get(k) for k in keep_inj} for r in results["injection"] if r["method"] == method],
            "unscored": results.get("unscored", {}).get(method, []),
            "source": "quadformer benchmark --profile field --shipped " + str(results["shipped"])}


def read_field(path: Path) -> dict[str, Any]:
    """A field run's results.json on a shipped set, or ValueError naming what is wrong."""
    import json

    try:
        res = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise ValueError(f"field: {path}: no such file") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"field: {path}: not a results.json ({e})") from None
    if not isinstance(res, dict) or not res.get("shipped") or not {"false_alarms", "injection"} <= set(res):
        raise ValueError(f"field: {path} is not a field run of a shipped set (`quadformer benchmark --profile "
                         "field --shipped SET`)")
    return res


def attach_field(doc: dict[str, Any], path: Path) -> str:
    """Put a field run's figures into the cards of the set it judged, after checking that it
    judged these very files; the set's name."""
    res = read_field(path)
    name = res.get("shipped")
    judged = res.get("shipped_files") or {}
    if not name or name not in doc["sets"]:
        raise ValueError(f"field: {path} is not a field run of a shipped set built here (`quadformer benchmark "
                         "--profile field --shipped SET`)")
    mine = {k: v["files"] for k, v in doc["detectors"].items() if v["set"] == name}
    if judged != mine:
        raise ValueError(f"field: {path} judged other files than the {name} set built now (checksums differ): "
                         "run the field benchmark again on these detectors")
    for k, v in doc["detectors"].items():
        if v["set"] == name:
            v["card"]["field"] = field_figures(res, v["method"])
    return name


def build(out: Path | None = None, cache_dir: Path = Path("runs/cache"), sets: list[str] | None = None,
          flights: int | None = None, seed: int = ZOO_SEED, progress: bool = True, workers: int | None = None,
          echo: Callable[[str], None] = print, field: Path | None = None,
          duration: float = 60.0, methods: list[str] | None = None) -> dict[str, Any]:
    """Build the recipes' detectors (``sets``: some of them, the others kept as they are in
    ``out``; ``flights`` per configuration instead of the recipes'; another ``seed``) into
    ``out`` (default: the package's ``detectors/pretrained/models``), replacing it once
    everything is written; returns the index.

    A set's default (what ``pretrained.load(set)`` and ``detect`` without ``--model`` give) is
    its method with the highest point-wise F1 on the validation flights at its false-alarm-budget
    threshold (the threshold a fielded detector alarms at: F1 there weighs how soon and how long an
    attack is flagged, and the false alarms the budget leaves), the recipe's order breaking ties.

    ``methods``: rebuild only these methods of ``sets`` (each must be in every chosen set's
    recipe); the sets' other detectors are kept, and must have been built from the very flights
    the rebuild simulates (same seed, flights and duration), else ValueError. The set's default
    is chosen again from the kept cards' validation figures and the rebuilt ones', and the set's
    entry records the rebuild (``rebuilt``: the methods and the command) beside its first build.

    ``duration``: seconds per simulated flight (the recipes' 60 s; shorter for a quick trial).
    ``field``: the results.json of a field run on the set's detectors (``benchmark --profile
    field --shipped SET``); its figures go into their cards where it judged the very files built
    (same checksums), else ValueError."""
    import shutil

    from quadformer.io import set_threads

    out = pretrained.ROOT if out is None else Path(out)
    known = [r.set for r in RECIPES]
    chosen = [r for r in RECIPES if sets is None or r.set in sets]
    unknown = sorted(set(sets or ()) - set(known))
    if unknown:
        raise ValueError(f"sets: unknown {', '.join(unknown)}; choose from {', '.join(known)}")
    if methods is not None:
        if not sets:
            raise ValueError("methods: name the sets whose methods to rebuild (--sets)")
        for r in chosen:
            odd = sorted(set(methods) - set(r.methods))
            if odd or not methods:
                raise ValueError(f"methods: {', '.join(odd) + ' not in the ' + r.set + ' set' if odd else 'none given'}"
                                 f"; choose from {', '.join(r.methods)}")
    if flights is not None and flights < 10:
        raise ValueError(f"flights: at least 10 per configuration (each part of the split needs flights), "
                         f"got {flights}")
    if seed == DEMO_SEED or seed < 100:
        raise ValueError(f"seed: {seed} is a seed benchmarks or the demo test on; the zoo's default is {ZOO_SEED}")
    if field is not None:
        read_field(field)          # a bad file fails before the build, not after it
    set_threads(THREADS)
    kept = _kept(out, {r.set for r in chosen}, methods) if sets is not None else {"sets": {}, "detectors": {}}
    if methods is not None:
        for r in chosen:
            if r.set not in kept["sets"]:
                raise ValueError(f"methods: no {r.set} set in {out} to keep the other methods of; "
                                 f"build the whole set (--sets {r.set} without --methods)")
    doc: dict[str, Any] = {"format": pretrained.FORMAT, "format_version": pretrained.FORMAT_VERSION,
                           "seed": seed, "sets": {}, "detectors": {},
                           "provenance": provenance({"zoo": seed}, None)}
    t_all = time.perf_counter()
    with atomic_dir(out, overwrite=True) as tmp:
        for name, entry in kept["detectors"].items():
            for f in entry["files"]:
                shutil.copy2(out / f, tmp / f)
        for r in RECIPES:
            others = {k: v for k, v in kept["detectors"].items() if v["set"] == r.set}
            if r in chosen:
                doc["sets"][r.set], built = _build_set(r, tmp, cache_dir, flights, seed, progress, workers, echo,
                                                       duration, methods, others)
                if methods is None:
                    doc["sets"][r.set]["provenance"] = doc["provenance"]    # a kept set keeps its own
                else:
                    old = kept["sets"][r.set]
                    doc["sets"][r.set].update(provenance=old.get("provenance"), rebuilt=[
                        *old.get("rebuilt", []), {"methods": list(methods), "provenance": doc["provenance"]}])
                merged = {**others, **built}
                doc["detectors"].update({f"{r.set}-{m}": merged[f"{r.set}-{m}"] for m in r.methods})
            elif r.set in kept["sets"]:
                doc["sets"][r.set] = kept["sets"][r.set]
                doc["detectors"].update(others)
        if field is not None:
            echo(f"field figures of the {attach_field(doc, field)} set from {field}")
        doc["build_seconds"] = round(time.perf_counter() - t_all, 1)
        write_json(tmp / "index.json", doc)
    return doc


def _check_kept(r: Recipe, methods: list[str], others: dict[str, Any], sim_doc: list[dict[str, Any]]) -> None:
    """A rebuild of ``methods`` keeps the set's ``others``: each other method of the recipe must be
    there, built from the flights ``sim_doc`` records, else ValueError."""
    missing = [m for m in r.methods if m not in methods and f"{r.set}-{m}" not in others]
    if missing:
        raise ValueError(f"methods: the {r.set} set has no {', '.join(missing)} to keep; rebuild the whole set "
                         f"(--sets {r.set} without --methods)")
    for name, e in others.items():
        if e["card"]["training"]["simulation"] != sim_doc:
            raise ValueError(f"methods: {name} was built from other flights than these (seed, flights or "
                             f"duration differ); rebuild the whole set (--sets {r.set} without --methods)")


def _build_set(r: Recipe, tmp: Path, cache_dir: Path, flights: int | None, seed: int, progress: bool,
               workers: int | None, echo: Callable[[str], None], duration: float = 60.0,
               methods: list[str] | None = None,
               others: dict[str, Any] | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
    """One recipe's detectors written into ``tmp``: (the set's index entry, its detectors' entries).
    ``methods``: only these, the set's ``others`` (kept entries) built from the same flights."""
    configs = r.configs(flights or r.flights, seed, duration)
    sim_doc = _simulation_doc(configs)
    others = others or {}
    if methods is not None:
        _check_kept(r, methods, others, json.loads(json.dumps(sim_doc)))   # as a card reads back: lists
    echo(f"{r.set}: simulating {sum(c.flights for _, c in configs)} flights ({len(configs)} configuration(s))")
    paths = ensure_configs(configs, cache_dir, progress=progress, workers=workers)
    parts, y_train, counts, sim = pooled_splits(paths)
    rate = float(configs[0][1].gps.rate_hz)
    built = {}
    picks = {e["method"]: e["card"]["training"]["validation_at_budget"]["f1"] or 0.0 for e in others.values()}
    for m in (r.methods if methods is None else [m for m in r.methods if m in methods]):
        name = f"{r.set}-{m}"
        t0 = time.perf_counter()
        tuned = tune(m, parts["train"], y_train, parts["val"], gps_rate_hz=rate, budget_per_hour=BUDGET_PER_HOUR)
        det = tuned.detector
        budget = det.budget_threshold_
        floor = r.field_threshold if m == r.default else None
        if floor is not None and floor > budget:
            budget = floor                  # the real clean flights' tails, which the simulation lacks
        det.calibrate(max(det.threshold_, budget) if floor is not None else det.threshold_, budget, zoo=name,
                      sim_config=sim, split_seed=SPLIT_SEED, label_fraction=LABEL_FRACTION,
                      configs=[n for n, _ in configs],
                      **({"field_threshold": floor, "field_source": r.field_source,
                          "sim_budget_threshold": det.budget_threshold_} if floor is not None else {}))
        t_tune = time.perf_counter() - t0
        val = _figures(parts["val"], tuned.val_scores, det.budget_threshold_, rate)
        picks[m] = val["f1"] or 0.0
        s = det.decision_function(parts["test"])
        det.save(tmp / f"{name}.qfm")
        files = sorted(p.name for p in tmp.glob(f"{name}.*"))
        test = parts["test"]
        card = {
            "method": m, "set": r.set, "sensors": r.sensors, "residues": r.residues, "about": r.about,
            "training": {"simulation": sim_doc, "split": {
                "rule": "by flight within each configuration, 60/20/20 stratified by attacked, pooled",
                "split_seed": SPLIT_SEED, "label_fraction": LABEL_FRACTION, **counts},
                "budget": "full (the method's default epochs and windows)", "params": tuned.params,
                "validation_f1": tuned.val_f1,
                "validation_at_budget": {k: val[k] for k in ("f1", "event_recall", "delay_median_s")},
                "threads": THREADS, "tune_seconds": round(t_tune, 1)},
            "rates": _rates(configs[0][1]),
            "calibration": {"budget_per_hour": BUDGET_PER_HOUR, "f1_threshold": det.threshold_,
                            "budget_threshold": det.budget_threshold_,
                            "rule": "f1: best point-wise F1 on the validation flights; budget: at most "
                                    f"{BUDGET_PER_HOUR:g} alarm run(s) per flight-hour on the clean validation "
                                    "flights"},
            "test": {"flights": int(test.flight_id.nunique()),
                     "attacked_flights": int(test.groupby("flight_id").label.max().sum()),
                     "flight_hours": len(test) / rate / 3600.0,
                     "at_f1_threshold": _figures(test, s, det.threshold_, rate),
                     "at_budget_threshold": _figures(test, s, det.budget_threshold_, rate)},
            "versions": package_versions(),
            "paper_profile": ({"source": "docs/results.md#paper-profile (quadformer benchmark --profile paper; a "
                                         "model per configuration, 360 training flights each)",
                               "f1": PAPER_PROFILE_F1[m]} if r.set == "vio" and m in PAPER_PROFILE_F1 else None),
            "field": None,
        }
        built[name] = {"method": m, "set": r.set, "files": {f: pretrained.sha256(tmp / f) for f in files},
                       "card": card}
        f, b = card["test"]["at_f1_threshold"], card["test"]["at_budget_threshold"]
        echo(f"  {name}: tuned in {t_tune:.0f} s; test F1 {f['f1']:.3f} at the F1 threshold; at the budget "
             f"threshold F1 {b['f1']:.3f} (validation {_fmt(val['f1'])}), event recall {_fmt(b['event_recall'])}")
    best = max(r.methods, key=lambda m: (picks[m], -r.methods.index(m)))
    rule = ("highest point-wise F1 on the validation flights at the false-alarm-budget threshold; the recipe's "
            "order on ties")
    if r.default is not None:
        echo(f"  {r.set}: default {r.set}-{r.default} by design (the validation flights' best: {r.set}-{best})")
        best, rule = r.default, f"by design: {r.default_reason} (the validation flights' best: {r.set}-{best})"
    else:
        echo(f"  {r.set}: default {r.set}-{best} (highest validation F1 at the budget threshold)")
    entry = {"sensors": r.sensors, "residues": r.residues, "formats": list(r.formats), "default": f"{r.set}-{best}",
             "about": r.about, "default_rule": rule}
    return entry, built


def _fmt(x) -> str:
    return "-" if x is None else f"{x:.2f}"
