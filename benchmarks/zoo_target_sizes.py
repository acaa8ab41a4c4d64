"""Event recall of shipped detectors on their zoo's own test flights, on the targets' sizes.

The model cards give each detector's event recall over every attacked test flight (offsets of 1
to 10 m, drifts of 0.05 to 2 m/s). The no-camera target is stated on offsets of at least 2 m and
drifts of at least 0.2 m/s; this re-scores the set's held-out test flights (the zoo's simulation,
from the dataset cache, split as the build splits them) with each shipped detector at its
budget threshold and counts the attacked flights alarmed between onset and end, by kind, on
those sizes:

    python benchmarks/zoo_target_sizes.py                          # magbaro-glr, -cusum, -chi2
    python benchmarks/zoo_target_sizes.py --set magbaro --detectors magbaro-glr

A flight's size: a bias's largest offset, a ramp's offset growth per second over the attack.
The datasets are simulated into ``--cache`` where they are not there yet (as ``zoo build`` does).
The last line printed is one JSON object.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

OFFSET_M = 2.0        # the targets' sizes
DRIFT_MS = 0.2


def sizes(test, scores: np.ndarray, threshold: float) -> list[tuple[str, float, bool, bool]]:
    """(kind, size, at the targets' sizes, alarmed) of each attacked flight of ``test``."""
    out = []
    for _, g in test.groupby("flight_id", sort=False):
        lab = g["label"].to_numpy() > 0
        if not lab.any():
            continue
        kind = str(g["attack_type"].to_numpy()[lab][0])
        off = np.linalg.norm(g[["atk_d_x", "atk_d_y", "atk_d_z"]].to_numpy(), axis=1)[lab]
        t = g["t"].to_numpy()[lab]
        if kind == "bias":
            size, big = float(off.max()), float(off.max()) >= OFFSET_M
        else:
            size = float((off[-1] - off[0]) / max(t[-1] - t[0], 1e-9))
            big = size >= DRIFT_MS
        out.append((kind, size, big, bool((scores[g.index.to_numpy()][lab] > threshold).any())))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--set", default="magbaro", help="a zoo set (default: %(default)s)")
    ap.add_argument("--detectors", default=None, help="comma-separated shipped names (default: the set's glr, "
                                                       "cusum and chi2 where it has them)")
    ap.add_argument("--cache", type=Path, default=Path("runs/cache"), help="dataset cache (default: %(default)s)")
    a = ap.parse_args()

    from quadformer.detectors import pretrained
    from quadformer.experiments.cache import ensure_configs
    from quadformer.experiments.zoo import ZOO_SEED, pooled_splits
    from quadformer.experiments.zoo_recipes import RECIPES

    recipe = {r.set: r for r in RECIPES}.get(a.set)
    if recipe is None:
        raise SystemExit(f"--set: unknown set {a.set!r}; choose one of {', '.join(r.set for r in RECIPES)}")
    names = a.detectors.split(",") if a.detectors else [f"{a.set}-{m}" for m in ("glr", "cusum", "chi2")
                                                          if m in recipe.methods]
    configs = recipe.configs(recipe.flights, ZOO_SEED, 60.0)
    parts, _, _, _ = pooled_splits(ensure_configs(configs, a.cache, progress=False))
    test = parts["test"]
    report = {"benchmark": "zoo_target_sizes", "set": a.set, "test_flights": int(test["flight_id"].nunique()),
              "offset_m": OFFSET_M, "drift_ms": DRIFT_MS, "detectors": {}}
    for name in names:
        det = pretrained.load(name, threshold="budget")
        rows = sizes(test, det.decision_function(test), float(det.threshold_))
        big = [r for r in rows if r[2]]
        by_kind = {k: {"recall": float(np.mean([r[3] for r in big if r[0] == k])),
                       "flights": sum(r[0] == k for r in big)} for k in sorted({r[0] for r in big})}
        entry = {"threshold": float(det.threshold_), "event_recall": float(np.mean([r[3] for r in rows])),
                 "attacked": len(rows), "event_recall_target_sizes": float(np.mean([r[3] for r in big])),
                 "at_target_sizes": len(big), "by_kind": by_kind}
        report["detectors"][name] = entry
        kinds = ", ".join(f"{k} {v['recall']:.2f} ({v['flights']})" for k, v in by_kind.items())
        print(f"{name}: threshold {entry['threshold']:.1f}; event recall {entry['event_recall']:.2f} of {len(rows)} "
              f"attacked; on the targets' sizes {entry['event_recall_target_sizes']:.2f} of {len(big)} ({kinds})")
    print(json.dumps(report))


if __name__ == "__main__":
    main()
