"""Where each detector's point-wise errors fall on the test flights of a benchmark run.

Reads the alarms a run kept (``<run>/scores/<config>.parquet``: ``flight_id``, ``t``,
``label`` and ``alarm_<method>`` per test step, at each method's F1 threshold) and splits
every attacked step an alarm misses into *early* (the first ``--early`` seconds of its
attack) and *late*, and every clean step an alarm covers into *after* (the ``--after``
seconds following an attack's end, where the filter reconverges and the persistent residues
still hold the attack) and *elsewhere*. Point-wise precision, recall and F1 follow from the
counts (those of the run's tables: raw, no point adjustment). Printed per configuration and
pooled; the last line printed is one JSON object.

    python benchmarks/errors.py RUN [--methods bht,cnn,lstm,quadformer] [--early 3] [--after 10]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd

from quadformer.evaluation.metrics import prf

COUNTS = ("tp", "miss_early", "miss_late", "fa_after", "fa_elsewhere")


def breakdown(scores: pd.DataFrame, method: str, early_s: float, after_s: float) -> dict[str, int]:
    """Counts of ``COUNTS`` for one method over the flights of ``scores``."""
    out = dict.fromkeys(COUNTS, 0)
    col = f"alarm_{method}"
    if col not in scores:
        raise KeyError(f"no alarms of method {method!r} in the scores (have: "
                       f"{', '.join(c[6:] for c in scores.columns if c.startswith('alarm_'))})")
    for _, g in scores.groupby("flight_id", sort=False):
        g = g.sort_values("t")
        t = g["t"].to_numpy()
        lab = g["label"].to_numpy() > 0
        alarm = g[col].to_numpy() > 0
        early = np.zeros_like(lab)
        after = np.zeros_like(lab)
        # each attack: a run of attacked steps
        edges = np.flatnonzero(np.diff(np.r_[0, lab.astype(np.int8), 0]))
        for start, stop in zip(edges[::2], edges[1::2]):
            early |= lab & (t >= t[start]) & (t < t[start] + early_s)
            after |= ~lab & (t > t[stop - 1]) & (t <= t[stop - 1] + after_s)
        out["tp"] += int((lab & alarm).sum())
        out["miss_early"] += int((lab & early & ~alarm).sum())
        out["miss_late"] += int((lab & ~early & ~alarm).sum())
        out["fa_after"] += int((after & alarm).sum())
        out["fa_elsewhere"] += int((~lab & ~after & alarm).sum())
    return out


def line(method: str, c: dict[str, int]) -> str:
    """The counts and the point-wise P / R / F1 they give."""
    p, r, f1 = prf(c["tp"], c["fa_after"] + c["fa_elsewhere"], c["miss_early"] + c["miss_late"])
    return f"  {method:20s} " + " ".join(f"{k} {c[k]:6d}" for k in COUNTS) + f"  P {p:.2f} R {r:.2f} F1 {f1:.2f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="a benchmark run's output directory")
    ap.add_argument("--methods", default=None, help="comma-separated (default: every method in the scores)")
    ap.add_argument("--early", type=float, default=3.0, help="seconds from an attack's start counted early")
    ap.add_argument("--after", type=float, default=10.0, help="seconds after an attack's end counted after")
    args = ap.parse_args()
    if args.early < 0 or args.after < 0:
        ap.error("--early and --after must be >= 0")
    files = sorted((args.run / "scores").glob("*.parquet"))
    if not files:
        ap.error(f"no scores in {args.run / 'scores'}: not a benchmark run's output directory")
    result: dict[str, dict[str, dict[str, int]]] = {}
    pooled: dict[str, dict[str, int]] = {}
    for f in files:
        scores = pd.read_parquet(f)
        methods = (args.methods.split(",") if args.methods
                   else [c[6:] for c in scores.columns if c.startswith("alarm_")])
        print(f"{f.stem}")
        result[f.stem] = {}
        for m in methods:
            try:
                c = breakdown(scores, m, args.early, args.after)
            except KeyError as e:
                ap.error(f"{f.name}: {e.args[0]}")
            result[f.stem][m] = c
            pooled.setdefault(m, dict.fromkeys(COUNTS, 0))
            for k in COUNTS:
                pooled[m][k] += c[k]
            print(line(m, c))
    print("pooled")
    for m, c in pooled.items():
        print(line(m, c))
    print(json.dumps({"run": str(args.run), "early_s": args.early, "after_s": args.after,
                      "configs": result, "pooled": pooled}))


if __name__ == "__main__":
    main()
