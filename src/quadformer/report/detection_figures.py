"""The detection benchmark's figures (PNG files, and inline for report.html): F1 per method and
configuration, detection delays, and an example attacked flight's residues, scores and alarms."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from quadformer.dataset import load_dataset
from quadformer.evaluation.metrics import flight_events
from quadformer.report.html import png


def figures(results: dict[str, Any], out: Path) -> dict[str, str]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    (out / "figures").mkdir(exist_ok=True)
    figs: dict[str, str] = {}
    methods = results["methods_run"]

    # F1 per method and configuration
    fig, ax = plt.subplots(figsize=(10, 3.8))
    names = [c["name"] for c in results["configs"]]
    w = 0.8 / max(len(methods), 1)
    for i, m in enumerate(methods):
        ax.bar(np.arange(len(names)) + i * w, [c["methods"][m]["f1"] for c in results["configs"]], w, label=m)
    ax.set_xticks(np.arange(len(names)) + 0.4 - w / 2, names, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("point-wise F1 (test)")
    ax.set_ylim(0, 1)
    ax.legend(ncol=len(methods), fontsize=8)
    figs["f1_by_config"] = png(fig)
    fig.savefig(out / "figures" / "f1_by_config.png", dpi=110, bbox_inches="tight")
    plt.close(fig)

    # detection delays
    fig, ax = plt.subplots(figsize=(6, 3.5))
    data, labels = [], []
    for m in methods:
        d = _delays(results, out, m)
        if len(d):
            data.append(d)
            labels.append(m)
    if data:
        ax.boxplot(data, tick_labels=labels)
    ax.set_ylabel("detection delay (s), test windows found")
    figs["delays"] = png(fig)
    fig.savefig(out / "figures" / "delays.png", dpi=110, bbox_inches="tight")
    plt.close(fig)

    # example flights: the first attacked test flight of each attack type, Model II
    for c in results["configs"]:
        if c.get("model") != "II" or c.get("noise") != "laplace":
            continue
        sc = pd.read_parquet(out / "scores" / f"{c['name']}.parquet")
        attacked = sc.groupby("flight_id").label.max()
        if not attacked.any():
            continue
        fid = attacked[attacked == 1].index[0]
        g = sc[sc.flight_id == fid]
        ds = load_dataset(c["dataset"]).flights
        d = ds[ds.flight_id == fid]
        fig, axes = plt.subplots(len(methods) + 1, 1, figsize=(9, 1.6 * (len(methods) + 1)), sharex=True)
        axes = np.atleast_1d(axes)
        axes[0].plot(d.t, d.res_gps_r_px, lw=0.8, label="innovation px")
        axes[0].plot(d.t, d.res_gps_r_py, lw=0.8, label="innovation py")
        axes[0].set_ylabel("residue (m)")
        axes[0].legend(fontsize=7, loc="upper left")
        for ax, m in zip(axes[1:], methods):
            ax.plot(g.t, g[f"score_{m}"], lw=0.8, color="k")
            ax.axhline(c["methods"][m]["threshold"], color="r", lw=0.8, ls="--")
            al = g[g[f"alarm_{m}"] == 1]
            ax.plot(al.t, np.full(len(al), c["methods"][m]["threshold"]), "r|", ms=6)
            ax.set_ylabel(m, fontsize=8)
            ax.set_yscale("symlog")
        for ax in axes:
            lab = g.label.to_numpy() == 1
            if lab.any():
                ax.axvspan(g.t.to_numpy()[lab][0], g.t.to_numpy()[lab][-1], color="orange", alpha=0.2)
        axes[-1].set_xlabel("t (s)")
        fig.suptitle(f"{c['name']}: test flight {fid} (shaded: attack window; red: threshold, alarms)", fontsize=9)
        key = f"example_{c['name']}"
        figs[key] = png(fig)
        fig.savefig(out / "figures" / f"{key}.png", dpi=110, bbox_inches="tight")
        plt.close(fig)
    return figs


def _delays(results, out: Path, method: str) -> list[float]:
    delays: list[float] = []
    for c in results["configs"]:
        p = out / "scores" / f"{c['name']}.parquet"
        if not p.exists():
            continue
        sc = pd.read_parquet(p)
        for _, g in sc.groupby("flight_id", sort=False):
            delays += flight_events(g.label.to_numpy(), g[f"alarm_{method}"].to_numpy(), g.t.to_numpy()).delays
    return delays
