"""Report of a resilience run: the four policies side by side, tables and trajectory figures."""

from __future__ import annotations

import html
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from quadformer.report._report import _png, _write

COLUMNS = {
    "max_dev_median_m": "max deviation from mission, median (m)",
    "max_dev_max_m": "max deviation, worst flight (m)",
    "est_err_rms_median_m": "estimate error RMS, median (m)",
    "est_err_max_max_m": "estimate error max, worst flight (m)",
    "excluded_during_attack": "attacks excluded",
    "exclusion_delay_median_s": "onset to exclusion, median (s)",
    "readmit_delay_median_s": "end to re-admission, median (s)",
    "readmit_delay_max_s": "end to re-admission, max (s)",
    "not_readmitted": "never re-admitted",
    "wrongly_excluded_fraction": "GPS wrongly excluded, clean flights (share of time)",
}


def policy_table(results: dict[str, Any]) -> pd.DataFrame:
    rows = []
    for c in results["configs"]:
        for p, m in c["policies"].items():
            rows.append({"config": c["name"], "policy": p, "attacked": m["attacked_flights"],
                         **{v: m.get(k) for k, v in COLUMNS.items()}})
    return pd.DataFrame(rows)


def overall_table(results: dict[str, Any]) -> pd.DataFrame:
    """Per policy over all configurations' flights."""
    per: dict[str, list[dict[str, Any]]] = {}
    for c in results["configs"]:
        for r in c["flights"]:
            per.setdefault(r["policy"], []).append(r)
    rows = []
    for p, fl in per.items():
        att = [r for r in fl if r["attacked"]]
        clean = [r for r in fl if not r["attacked"]]

        def vals(key, src=att):
            return [r[key] for r in src if r.get(key) is not None]

        dev = vals("max_dev_m")
        rd = vals("readmit_delay_s")
        rows.append({
            "policy": p, "attacked flights": len(att),
            "max deviation median (m)": np.median(dev) if dev else None,
            "max deviation p95 (m)": np.percentile(dev, 95) if dev else None,
            "max deviation worst (m)": np.max(dev) if dev else None,
            "estimate error RMS median (m)": np.median(vals("est_err_rms_m")) if att else None,
            "onset to exclusion median (s)": np.median(vals("exclusion_delay_s")) if vals("exclusion_delay_s") else None,
            "end to re-admission median (s)": np.median(rd) if rd else None,
            "end to re-admission p95 (s)": np.percentile(rd, 95) if rd else None,
            "never re-admitted": sum(r.get("readmitted") is False for r in att),
            "wrongly excluded (clean time)": np.mean(vals("excluded_fraction", clean)) if clean else None,
        })
    return pd.DataFrame(rows)


def _trajectory_figure(traj: pd.DataFrame, flight: int, policies: list[str], title: str):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(policies), figsize=(4 * len(policies), 4))
    for ax, p in zip(np.atleast_1d(axes), policies):
        g = traj[(traj.policy == p) & (traj.flight_id == flight)]
        lab = g.label.to_numpy() == 1
        if lab.any():   # the attack window, from 5 s before to 15 s after
            t = g.t.to_numpy()
            g = g[(t >= t[lab][0] - 5.0) & (t <= t[lab][-1] + 15.0)]
        att = g.label.to_numpy() == 1
        ax.plot(g.ref_pos_x, g.ref_pos_y, color="0.6", lw=2, label="mission")
        ax.plot(g.true_pos_x, g.true_pos_y, color="C0", lw=1.2, label="true")
        ax.plot(g.est_pos_x, g.est_pos_y, color="C1", lw=1, ls="--", label="estimate")
        ax.scatter(g.gps_pos_x[att], g.gps_pos_y[att], s=3, color="C3", label="spoofed GPS")
        excl = ~g.fused.to_numpy(bool)
        ax.scatter(g.true_pos_x[excl], g.true_pos_y[excl], s=4, color="k", marker="x", label="GPS excluded")
        ax.set_title(p)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("x (m)")
    np.atleast_1d(axes)[0].set_ylabel("y (m)")
    np.atleast_1d(axes)[0].legend(fontsize=7, loc="best")
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def write_resilience_report(results: dict[str, Any], out: Path) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    table = policy_table(results)
    overall = overall_table(results)
    _write(out / "policies.csv", table.to_csv(index=False))
    _write(out / "overall.csv", overall.to_csv(index=False))
    (out / "figures").mkdir(exist_ok=True)
    parts = [f"<h1>quadformer resilience: profile {html.escape(results['profile'])}, detector "
             f"{html.escape(results['detector'])} (threshold: {html.escape(results.get('threshold_rule', 'f1'))})</h1>",
             f"<p>{html.escape(results['protocol'])}"
             + (f" (the first {results['max_test_flights']} test flights of each configuration)"
                if results.get("max_test_flights") else "")
             + ". Policies: naive (always fuse GPS), px4 (5-sigma "
             "innovation gate, reset to GPS after 7 s of rejections), resilient (exclude GPS on the detector's "
             "alarm, re-admit after it has been clear and GPS has agreed with the estimate for the hold time, "
             "blended), oracle (excludes exactly the spoofed fixes). Deviations are of the true vehicle from "
             "its mission during the attack window.</p>",
             "<h2>All configurations</h2>",
             overall.to_html(index=False, float_format=lambda v: f"{v:.2f}", na_rep="-", border=0, classes="t"),
             "<h2>Per configuration</h2>",
             table.to_html(index=False, float_format=lambda v: f"{v:.3g}", na_rep="-", border=0, classes="t")]
    for c in results["configs"]:
        path = out / "trajectories" / f"{c['name']}.parquet"
        if not path.exists():
            continue
        naive = [r for r in c["flights"] if r["policy"] == results["policies"][0] and r["attacked"]]
        if not naive:
            continue
        worst = max(naive, key=lambda r: r["max_dev_m"])["flight_id"]   # the attack that hurt most
        traj = pd.read_parquet(path)
        fig = _trajectory_figure(traj, worst, results["policies"],
                                 f"{c['name']}: test flight {worst} (attack that moved the naive vehicle most), "
                                 "from 5 s before the attack to 15 s after")
        fig.savefig(out / "figures" / f"trajectory_{c['name']}.png", dpi=110, bbox_inches="tight")
        b64 = _png(fig)
        plt.close(fig)
        parts.append(f"<h3>{html.escape(c['name'])}</h3><img src='data:image/png;base64,{b64}'/>")
    parts.append("<h2>Versions</h2><pre>" + html.escape(str(results.get("versions", {}))) + "</pre>")
    style = ("<style>body{font-family:sans-serif;max-width:1300px;margin:auto}"
             "table.t{border-collapse:collapse;font-size:12px}table.t td,table.t th{padding:2px 6px;"
             "border-bottom:1px solid #ddd;text-align:right}img{max-width:100%}</style>")
    doc = (f"<!doctype html><html><head><meta charset='utf-8'><title>quadformer resilience</title>{style}"
           f"</head><body>{''.join(parts)}</body></html>")
    _write(out / "report.html", doc)
    return out / "report.html"
