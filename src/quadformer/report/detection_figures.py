"""The detection benchmark's figures (PNG files, and inline for report.html): F1 per method and
configuration with its interval, detection delay against false alarms per hour, the delays'
spread, and example attacked flights' residues, scores and alarms."""

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

    # F1 per method and configuration, with its 95% bootstrap interval over test flights
    names = [c["name"] for c in results["configs"]]
    fig, ax = plt.subplots(figsize=(11, 4))
    w = 0.8 / max(len(methods), 1)
    for i, m in enumerate(methods):
        f1 = np.array([c["methods"][m]["f1"] for c in results["configs"]], dtype=float)
        ci = np.array([c["methods"][m].get("f1_ci95") or (np.nan, np.nan) for c in results["configs"]], dtype=float)
        x = np.arange(len(names)) + i * w - 0.4 + w / 2
        has = np.isfinite(ci).all(axis=1)          # the interval as computed (it need not hold the point)
        ax.vlines(x[has], ci[has, 0], ci[has, 1], color=_colour(i), lw=1)
        ax.plot(x, f1, _marker(i), ms=4, color=_colour(i), label=m)
    ax.set_xticks(np.arange(len(names)), names, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("point-wise F1 (test), 95% interval")
    ax.set_ylim(0, 1.02)
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    figs["f1_by_config"] = png(fig)
    fig.savefig(out / "figures" / "f1_by_config.png", dpi=110, bbox_inches="tight")
    plt.close(fig)

    # detection delay against false alarms per clean flight-hour, a point per method and configuration
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for i, m in enumerate(methods):
        fa = [c["methods"][m].get("false_alarms_per_hour", np.nan) for c in results["configs"]]
        delay = [c["methods"][m].get("delay_median_s", np.nan) for c in results["configs"]]
        ax.plot(np.asarray(fa, dtype=float) + 0.1, np.asarray(delay, dtype=float), _marker(i), ms=5, alpha=0.8,
                color=_colour(i), label=m)
    ax.set_xscale("log")
    ax.set_xlabel("false alarms per clean test flight-hour (+0.1, log scale)")
    ax.set_ylabel("median detection delay (s)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax.set_title("each point: a method on one configuration; lower left is better", fontsize=9)
    figs["delay_vs_false_alarms"] = png(fig)
    fig.savefig(out / "figures" / "delay_vs_false_alarms.png", dpi=110, bbox_inches="tight")
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
        fig, axes = plt.subplots(len(methods) + 1, 1, figsize=(9, 1.6 * (len(methods) + 1)), sharex=True,
                                 layout="constrained")
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


def _colour(i: int) -> str:
    return f"C{i % 10}"


def _marker(i: int) -> str:
    """A marker per ten methods, so that methods sharing a colour differ in shape."""
    return "osD^v"[(i // 10) % 5]


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
