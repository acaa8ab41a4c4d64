"""Tables and report of the field benchmark: false alarms on clean real flights, GPS trouble, injected spoofs.

Opens with the figures (false alarms per in-air hour by method with their intervals, delay
against false alarms, one example flight per kind of log), then the tables: false alarms,
injected spoofs, GPS trouble, the receiver's degraded alerts, the logs read and refused.
"""

from __future__ import annotations

import html
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from quadformer.io import atomic_write_text
from quadformer.logs.calibration import poisson_interval
from quadformer.report.html import img, page, png, table, versions

BIG_OFFSET_M = 2.0          # the targets' offsets and drifts
BIG_DRIFT_MPS = 0.2
OFFSET_KINDS = ("bias", "capture")      # injections sized by an offset (m); the others by a drift rate (m/s)
#: s in the air after which a self-normalising detector has calibrated (glr: its longest window, 4 s,
#: its reference, 3 s, and its calib_min_s, 20 s, rounded up): the spoofs that began later are
#: counted apart (``recall_settled``)
SETTLED_AIR_S = 30.0
PHASE_COLOURS = {"ground": "#dddddd", "transition": "#ffe9b3"}


def clean_summary(per_log: pd.DataFrame) -> pd.DataFrame:
    """Spoofing alerts in air per in-air hour on the clean logs, by method and threshold, with
    the exposure and a Poisson 95% interval; ground, transition and degraded alerts beside them."""
    out = []
    clean = per_log[per_log["clean"]]
    for (m, thr), g in clean.groupby(["method", "threshold"], sort=False):
        hours = float(g["air_hours"].sum())
        n = int(g["spoofing_air"].sum())
        lo, hi = poisson_interval(n, hours) if hours > 0 else (float("nan"), float("nan"))
        out.append({"method": m, "threshold": thr, "logs": len(g), "air_hours": hours, "spoofing_air": n,
                    "per_air_hour": n / hours if hours > 0 else float("nan"), "ci_low": lo, "ci_high": hi,
                    "ground": int(g["spoofing_ground"].sum()), "transition": int(g["spoofing_transition"].sum()),
                    "degraded": int(g["degraded"].sum())})
    return pd.DataFrame(out)


def trouble_summary(per_log: pd.DataFrame) -> pd.DataFrame:
    """On the logs with GPS trouble: alerts inside the windows by kind (the spoofing alerts also by
    phase: in the air, in a take-off or landing transition), spoofing alerts outside."""
    bad = per_log[~per_log["clean"]]
    if not len(bad) or "windows" not in bad:
        return pd.DataFrame()
    out = []
    for (m, thr), g in bad.groupby(["method", "threshold"], sort=False):
        out.append({"method": m, "threshold": thr, "logs": len(g), "windows": int(g["windows"].sum()),
                    "in_window_degraded": int(g["in_window_degraded"].sum()),
                    "in_window_spoofing": int(g["in_window_spoofing"].sum()),
                    **{k: int(g[k].sum()) for k in ("in_window_spoofing_air", "in_window_spoofing_transition")
                       if k in g},
                    "outside_spoofing_air": int(g["outside_spoofing_air"].sum()),
                    "air_hours": float(g["air_hours"].sum())})
    return pd.DataFrame(out)


def injection_summary(df: pd.DataFrame) -> pd.DataFrame:
    """Event recall, delays and offsets by method, threshold and attack kind; ``recall_big`` on the
    targets' sizes (offsets >= 2 m, drifts >= 0.2 m/s), ``recall_floor`` on those at or above both
    the targets' size and the log's physical floor (the ``floor`` column, where the rows have it),
    with the median delay of those detected (``floor_delay_median_s``) and the share detected within
    3 s (``recall_floor_3s``); ``recall_tail`` likewise against the floor with the log's own tails
    (``floor_tail``, ``tail_injected``); ``recall_settled`` on the spoofs that began after ``SETTLED_AIR_S`` in
    the air (the rows' ``air_before_s``), when a detector that normalises itself in the air has
    calibrated (``glr``: its windows, reference and ``calib_min_s``), beside ``recall_early`` on
    those before."""
    out = []
    for (m, thr, kind), g in df.groupby(["method", "threshold", "kind"], sort=False):
        target = BIG_OFFSET_M if kind in OFFSET_KINDS else BIG_DRIFT_MPS
        big = g[g["size"] >= target]
        d = g["delay_s"].dropna().to_numpy(dtype=float)
        off = g["offset_at_detection_m"].dropna().to_numpy(dtype=float)
        row = {"method": m, "threshold": thr, "kind": kind, "injected": len(g),
               "event_recall": float(g["detected"].mean()),
               "recall_big": float(big["detected"].mean()) if len(big) else float("nan"),
               "big_injected": len(big),
               "delay_median_s": float(np.median(d)) if len(d) else float("nan"),
               "delay_p95_s": float(np.percentile(d, 95)) if len(d) else float("nan"),
               "offset_median_m": float(np.median(off)) if len(off) else float("nan")}
        if "air_before_s" in g.columns:
            late = g["air_before_s"].to_numpy(dtype=float) >= SETTLED_AIR_S
            row.update({"settled_injected": int(late.sum()),
                        "recall_settled": float(g["detected"][late].mean()) if late.any() else float("nan"),
                        "recall_early": float(g["detected"][~late].mean()) if (~late).any() else float("nan")})
        at = _at_floor(g, "floor", target)
        if at is not None:
            fd = at["delay_s"].dropna().to_numpy(dtype=float)
            row.update({"floor_injected": len(at),
                        "recall_floor": float(at["detected"].mean()) if len(at) else float("nan"),
                        "recall_floor_3s": float((at["delay_s"].fillna(np.inf) <= 3.0).mean()) if len(at)
                        else float("nan"),
                        "floor_delay_median_s": float(np.median(fd)) if len(fd) else float("nan")})
        at = _at_floor(g, "floor_tail", target)
        if at is not None:
            row.update({"tail_injected": len(at),
                        "recall_tail": float(at["detected"].mean()) if len(at) else float("nan")})
        out.append(row)
    return pd.DataFrame(out)


def _at_floor(g: pd.DataFrame, column: str, target: float) -> pd.DataFrame | None:
    """The rows of ``g`` whose size is at or above both ``target`` and their log's floor in ``column``;
    None where no row has that floor."""
    if column not in g.columns or not g[column].notna().any():
        return None
    floor = g[column].to_numpy(dtype=float)
    return g[np.isfinite(floor) & (g["size"].to_numpy(dtype=float) >= np.fmax(floor, target))]


def false_alarm_figure(fa: pd.DataFrame):
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 3.6))
    methods = list(dict.fromkeys(fa["method"]))
    x = np.arange(len(methods))
    for k, (thr, colour) in enumerate((("sim", "#4c72b0"), ("calibrated", "#dd8452"))):
        g = fa[fa["threshold"] == thr].set_index("method").reindex(methods)
        rate = g["per_air_hour"].to_numpy(dtype=float)
        lo = np.maximum(rate - g["ci_low"].to_numpy(dtype=float), 0)
        hi = np.maximum(g["ci_high"].to_numpy(dtype=float) - rate, 0)
        ax.errorbar(x + (k - 0.5) * 0.3, np.maximum(rate, 0.05), yerr=[np.minimum(lo, rate), hi], fmt="o",
                    color=colour, capsize=3, label=f"{thr} threshold")
    ax.axhline(1.0, color="k", lw=0.8, ls="--", label="target 1/h")
    ax.set_yscale("log")
    ax.set_xticks(x, methods, rotation=30)
    ax.set_ylabel("spoofing alerts per in-air hour")
    ax.set_title(f"Clean real flights ({fa['air_hours'].iloc[0]:.2f} in-air hours; 95% Poisson intervals; "
                 "0 drawn at 0.05)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def delay_figure(fa: pd.DataFrame, inj: pd.DataFrame):
    import matplotlib.pyplot as plt

    kinds = list(dict.fromkeys(inj["kind"]))
    fig, axes = plt.subplots(1, len(kinds), figsize=(5 * len(kinds), 3.8), squeeze=False)
    for ax, kind in zip(axes[0], kinds):
        for thr, marker in (("sim", "o"), ("calibrated", "s")):
            for _, r in inj[(inj["kind"] == kind) & (inj["threshold"] == thr)].iterrows():
                f = fa[(fa["method"] == r["method"]) & (fa["threshold"] == thr)]
                if not len(f):
                    continue
                ax.scatter(max(float(f["per_air_hour"].iloc[0]), 0.05), r["delay_median_s"], marker=marker, s=20)
                ax.annotate(f"{r['method']} ({r['event_recall']:.2f})", (max(float(f["per_air_hour"].iloc[0]), 0.05),
                            r["delay_median_s"]), fontsize=6)
        ax.set_xscale("log")
        ax.set_xlabel("spoofing alerts per in-air hour (clean flights)")
        ax.set_ylabel("median delay (s)")
        ax.set_title(f"injected {kind}: delay against false alarms (event recall); o sim, s calibrated", fontsize=8)
    fig.tight_layout()
    return fig


def example_figure(ex: dict[str, Any]):
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 2.6))
    t = np.asarray(ex["t"], dtype=float)
    phase = np.asarray(ex["phase"], dtype=object)
    for name, colour in PHASE_COLOURS.items():
        on = phase == name
        if on.any():
            ax.fill_between(t, 0, 1, where=on, transform=ax.get_xaxis_transform(), color=colour, lw=0,
                            label=name)
    for a, b in ex.get("windows", []):
        ax.axvspan(a, b, color="#f4a6a6", alpha=0.5, lw=0)
    if ex.get("attack") is not None:
        ax.axvspan(*ex["attack"], color="#b5d9a8", alpha=0.6, lw=0, label="injected spoof")
    ax.plot(t, ex["score"], lw=0.8, color="k")
    ax.axhline(ex["threshold"], color="r", lw=0.8, ls="--", label="threshold")
    for a in ex["alerts"]:
        ax.axvline(a["start_s"], color="#c44e52" if a["kind"] == "spoofing" else "#8172b2", lw=1.2)
    ax.set_yscale("symlog")
    ax.set_xlabel("t (s, from the log's first sensor sample)")
    ax.set_title(ex["title"], fontsize=9)
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    return fig


def write_field_report(results: dict[str, Any], per_log: pd.DataFrame, injections: pd.DataFrame,
                       examples: list[dict[str, Any]], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fa = pd.DataFrame(results["false_alarms"])
    inj = pd.DataFrame(results["injection"])
    parts = ["<h1>Field benchmark: real flight logs</h1>",
             f"<p>{len(results['read'])} logs read, {len(results['refused'])} refused. Detectors trained in "
             "simulation only (fleet noise from the clean logs); thresholds: the simulation's (<i>sim</i>) and "
             f"calibrated on the other clean logs at {results['plan']['budget_per_hour']:g} false alarm per "
             "in-air hour (<i>calibrated</i>, the scored log left out). Alerts are counted in air; ground and "
             "take-off or landing transition alerts, and alerts typed <i>degraded</i> (the receiver's own signs), "
             "apart.</p>"]
    figs = []
    if len(fa):
        figs.append(false_alarm_figure(fa))
    if len(inj) and len(fa):
        figs.append(delay_figure(fa, inj))
    figs += [example_figure(ex) for ex in examples]
    for f in figs:
        parts.append(img(png(f)))
        plt.close(f)
    parts.append("<h2>False alarms on clean flights</h2>" + (table(fa) if len(fa) else "<p>no clean log</p>"))
    parts.append("<h2>Spoofs injected in air</h2><p>recall_big: offsets of at least 2 m (bias, capture) and "
                 "drifts of at least 0.2 m/s (ramp, drift switched on at once, drift-accel accelerating in). "
                 f"recall_settled: the spoofs that began after {SETTLED_AIR_S:g} s in the air, when a detector "
                 "that normalises itself in the air has calibrated; recall_early: those before.</p>"
                 + (table(inj) if len(inj) else "<p>none</p>"))
    trouble = pd.DataFrame(results.get("troubles", []))
    parts.append("<h2>Logs with GPS trouble</h2>" + (table(trouble) if len(trouble) else "<p>none</p>"))
    rec = pd.DataFrame(results.get("receiver", []))
    parts.append("<h2>Receiver signs: a degraded alert within 2 s</h2>" + (table(rec) if len(rec) else "<p>none</p>"))
    parts.append("<details><summary>Per log</summary>" + table(per_log, index=False) + "</details>")
    read = pd.DataFrame(results["read"]).drop(columns=["notes"], errors="ignore")
    parts.append("<h2>Logs read</h2>" + table(read, index=False))
    if results["refused"]:
        parts.append("<h2>Logs refused</h2><ul>" + "".join(
            f"<li>{html.escape(r['log'])}: {html.escape(r['reason'])}</li>" for r in results["refused"]) + "</ul>")
    parts.append(versions(results.get("versions")))
    atomic_write_text(path, page("quadformer field benchmark", parts, width_px=1400))
    return path
