"""Report of a resilience run: the four policies side by side, tables and trajectory figures."""

from __future__ import annotations

import html
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from quadformer.evaluation.resilience import summarize_policy
from quadformer.io import atomic_write_text
from quadformer.report.html import img, page, png, table, versions

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
    "stale_readmissions": "re-admissions under a standing alarm",
    "wrongly_excluded_fraction": "GPS wrongly excluded, clean flights (share of time)",
    "exclusion_precision": "exclusion precision (vs spoofed)",
    "exclusion_recall": "exclusion recall (vs spoofed)",
    "exclusion_f1": "exclusion F1 (vs spoofed)",
}


def policy_table(results: dict[str, Any]) -> pd.DataFrame:
    rows = []
    for c in results["configs"]:
        for p, m in c["policies"].items():
            rows.append({"config": c["name"], "policy": p, "attacked": m["attacked_flights"],
                         **{v: m.get(k) for k, v in COLUMNS.items()}})
    return pd.DataFrame(rows)


# the all-configurations table: policy summary key -> column title
OVERALL = {
    "attacked_flights": "attacked flights",
    "max_dev_median_m": "max deviation median (m)",
    "max_dev_p95_m": "max deviation p95 (m)",
    "max_dev_max_m": "max deviation worst (m)",
    "est_err_rms_median_m": "estimate error RMS median (m)",
    "exclusion_delay_median_s": "onset to exclusion median (s)",
    "readmit_delay_median_s": "end to re-admission median (s)",
    "readmit_delay_p95_s": "end to re-admission p95 (s)",
    "not_readmitted": "never re-admitted",
    "stale_readmissions": "stale re-admissions",
    "wrongly_excluded_fraction": "wrongly excluded (clean time)",
    "exclusion_precision": "exclusion P",
    "exclusion_recall": "exclusion R",
    "exclusion_f1": "exclusion F1",
}


def overall_table(results: dict[str, Any]) -> pd.DataFrame:
    """Per policy over all configurations' flights."""
    per: dict[str, list[dict[str, Any]]] = {}
    for c in results["configs"]:
        for r in c["flights"]:
            per.setdefault(r["policy"], []).append(r)
    rows = []
    for p, flights in per.items():
        summary = summarize_policy(flights)
        rows.append({"policy": p, **{title: summary[k] for k, title in OVERALL.items()}})
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


def _stale_text(adm: dict[str, Any]) -> str:
    """The stale-alarm path of the resilient policy's re-admission, as run (none in results
    written before it existed, or with ``stale_hold_s`` infinite)."""
    stale = adm.get("stale_hold_s")
    if stale is None or not np.isfinite(stale):
        return ""
    return (f", or, under an alarm standing since its onset, after GPS has agreed for {stale:g} s (that alarm "
            "then no longer excludes GPS; a new onset or a fix outside the gate does)")


def write_resilience_report(results: dict[str, Any], out: Path) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    per_config = policy_table(results)
    overall = overall_table(results)
    atomic_write_text(out / "policies.csv", per_config.to_csv(index=False))
    atomic_write_text(out / "overall.csv", overall.to_csv(index=False))
    (out / "figures").mkdir(exist_ok=True)
    adm = results["admission"]
    parts = [f"<h1>quadformer resilience: profile {html.escape(results['profile'])}, detector "
             f"{html.escape(results['detector'])} (threshold: {html.escape(results.get('threshold_rule', 'f1'))})</h1>",
             f"<p>{html.escape(results['protocol'])}"
             + (f" (the first {results['max_test_flights']} test flights of each configuration)"
                if results.get("max_test_flights") else "")
             + f". Policies: naive (always fuse GPS), px4 ({adm['gate_sigma']:g}-sigma innovation gate, reset "
             f"to GPS after {adm['reset_after_s']:g} s of rejections), resilient (exclude GPS on the detector's "
             f"alarm, re-admit after it has been clear and GPS has agreed with the estimate for "
             f"{adm['hold_s']:g} s{_stale_text(adm)}, blended over {adm['blend_s']:g} s), "
             "oracle (excludes exactly the spoofed "
             "fixes). Deviations are of the true vehicle from its mission during the attack window. Exclusion "
             "P/R/F1: every GPS step of every flight (attacked and clean) is a prediction, GPS excluded, "
             "against the truth, GPS spoofed (point-wise, no adjustment; steps still excluded after an attack "
             "ends are false positives); the oracle scores 1 by construction.</p>",
             "<h2>All configurations</h2>",
             table(overall, index=False)]
    trajectories: list[str] = []
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
        b64 = png(fig)
        plt.close(fig)
        trajectories.append(f"<h3>{html.escape(c['name'])}</h3>{img(b64)}")
    # the figures before the long tables: one attacked flight under every policy, the others folded
    if trajectories:
        parts.append("<h2>An attacked flight under each policy</h2>" + trajectories[0])
    parts.append("<details><summary><h2 style='display:inline'>Per configuration</h2></summary>"
                 + table(per_config, ".3g", index=False) + "</details>")
    if len(trajectories) > 1:
        parts.append("<details><summary><h2 style='display:inline'>The other configurations' flights</h2>"
                     "</summary>" + "".join(trajectories[1:]) + "</details>")
    parts.append(versions(results.get("versions")))
    doc = page("quadformer resilience", parts, width_px=1300)
    atomic_write_text(out / "report.html", doc)
    return out / "report.html"
