"""Attack typing by shape: how often the type is right, some seconds into each attack, and its cost.

On a dataset with mixed attacks (simulated: every flight attacked, each kind drawn from all
six, Model and noise as given; or the datasets of ``--data``, pooled), the shape typer (``detectors.attack_types``)
types every attacked flight ``--lags`` seconds after the first attacked step, from the flight
up to that step. Printed: per lag, the share typed right and the confusion matrix (rows true,
columns typed); the median and p99 time of one typing (one thread). The last line printed is
one JSON object. The typer learns nothing, so the whole dataset is its test set.

    python benchmarks/attack_types.py [--flights 160] [--model I] [--noise exponential]
                                      [--seed 9001] [--lags 2,5,10] [--data DIR ...]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--flights", type=int, default=160)
    ap.add_argument("--model", default="I")
    ap.add_argument("--noise", default="exponential")
    ap.add_argument("--sensors", default="gps+imu+vio")
    ap.add_argument("--seed", type=int, default=9001)
    ap.add_argument("--lags", default="2,5,10", help="seconds after the first attacked step, comma-separated")
    ap.add_argument("--data", type=Path, nargs="+", default=None,
                    help="existing dataset directories, pooled (else simulated)")
    args = ap.parse_args()
    torch.set_num_threads(1)

    from quadformer import load_dataset, simulate
    from quadformer.config import AttackConfig, SimConfig
    from quadformer.detectors import ShapeTyper

    lags = [float(x) for x in args.lags.split(",")]
    if args.data is not None:
        sets = [load_dataset(d) for d in args.data]
        what = ", ".join(map(str, args.data))
    else:
        cfg = SimConfig(model=args.model, noise=args.noise, sensors=args.sensors, flights=args.flights,
                        duration=60.0, seed=args.seed, attack=AttackConfig(kind="mix", fraction=1.0))
        t0 = time.perf_counter()
        sets = [simulate(cfg)]
        what = f"simulated: {args.flights} flights, model {args.model}, {args.noise}, {args.sensors}, seed {args.seed}"
        print(f"simulated {args.flights} flights in {time.perf_counter() - t0:.0f} s")
    typer = ShapeTyper()
    rows, seconds = [], []
    flights = (g for ds in sets for _, g in ds.flights.groupby("flight_id", sort=False))
    for g in flights:
        g = g.reset_index(drop=True)
        attacked = np.flatnonzero(g.label.to_numpy() == 1)
        if not len(attacked):
            continue
        true = str(g.attack_type.iloc[attacked[0]])
        f = typer.prepare(g)
        rate = 1.0 / float(np.median(np.diff(g.t.to_numpy())))
        for lag in lags:
            k = attacked[0] + int(round(lag * rate))
            if k >= len(g) or g.label.iloc[k] == 0 and true != "intermittent":
                continue                          # the attack is over (an intermittent one may be off)
            t0 = time.perf_counter()
            kind, _ = typer.type_at(f, k)
            seconds.append(time.perf_counter() - t0)
            rows.append((lag, true, kind))
    r = pd.DataFrame(rows, columns=["lag", "true", "typed"])
    out = {"data": what, "per_lag": {}, "typing_ms_p50": float(np.median(seconds) * 1e3),
           "typing_ms_p99": float(np.percentile(seconds, 99) * 1e3)}
    for lag, q in r.groupby("lag"):
        right = int((q.true == q.typed).sum())
        out["per_lag"][f"{lag:g}"] = {"right": right, "typed": len(q), "share": right / len(q)}
        print(f"\n{lag:g} s after the onset: {right}/{len(q)} right ({right / len(q):.2f})")
        print(pd.crosstab(q.true, q.typed).to_string())
    print(f"\none typing: p50 {out['typing_ms_p50']:.1f} ms, p99 {out['typing_ms_p99']:.1f} ms")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
