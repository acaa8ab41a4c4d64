"""Table and report of the stealth benchmark (``experiments.stealth``): how far an attacker who
knows the detector moves the vehicle before anything alarms.

The page opens with the envelope curves (the median deviation unseen against the time since the
onset, one line per detector, a panel per sensor set and attacker, the physical bound dashed),
then the table: median / worst deviation unseen by each horizon, the flights still hidden at the
last, the bound and the worst as a ratio to it; then what each run's flights did.
"""

from __future__ import annotations

import html
from pathlib import Path
from typing import Any

import pandas as pd

from quadformer.io import atomic_write_text
from quadformer.report.html import img, page, png, table, versions


def attacker(run: dict[str, Any]) -> str:
    """A run's attacker as the tables name it: its knowledge, and the white box's margin."""
    return run["knowledge"] + (f" {run['margin']:g}" if run["margin"] else "")


def stealth_table(results: dict[str, Any]) -> pd.DataFrame:
    """One row per detector, knowledge and margin: the median and worst deviation unseen by each
    horizon, the share of flights still hidden at the last, the bound and the ratio to it."""
    horizons = tuple(results["plan"]["horizons"])
    rows = []
    for r in results["runs"]:
        s, b = r["summary"], results["bounds"][r["set"]]
        row = {"detector": r["detector"], "attacker": attacker(r)}
        for T in horizons:
            row[f"{T:g} s"] = f"{s[f'deviation_median_{T:g}']:.1f} / {s[f'deviation_worst_{T:g}']:.1f}"
        last = f"{max(horizons):g}"
        row[f"hidden at {last} s"] = f"{s[f'hidden_{last}']:.0%}"
        row[f"bound {last} s"] = f"{b[last]:.1f}"
        row["worst / bound"] = f"{s[f'deviation_worst_{last}'] / b[last]:.1f}"
        rows.append(row)
    return pd.DataFrame(rows)



def _curves(results: dict[str, Any]) -> str:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    horizons = [float(h) for h in results["plan"]["horizons"]]
    runs = results["runs"]
    panels = sorted({(r["set"], attacker(r)) for r in runs})
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.6), squeeze=False)
    for ax, (set_name, label) in zip(axes[0], panels):
        for r in runs:
            if r["set"] != set_name or attacker(r) != label:
                continue
            s = r["summary"]
            ax.plot([0.0, *horizons], [0.0, *[s[f"deviation_median_{h:g}"] for h in horizons]], "o-", ms=3,
                    lw=1, label=r["detector"])
        b = results["bounds"][set_name]
        ax.plot([0.0, *horizons], [0.0, *[b[f"{h:g}"] for h in horizons]], "k--", lw=1, label="physical bound")
        ax.set_title(f"{set_name}, {label} box", fontsize=9)
        ax.set_xlabel("s since the onset")
        ax.set_ylabel("deviation unseen (m, median)")
        ax.legend(fontsize=6)
    fig.tight_layout()
    b64 = png(fig)
    plt.close(fig)
    return img(b64)


def write_stealth_report(results: dict[str, Any], path: Path) -> Path:
    plan = results["plan"]
    flights = pd.DataFrame([{"detector": r["detector"], "attacker": attacker(r), **f}
                            for r in results["runs"] for f in r["flights"]])
    parts = [
        "<h1>quadformer stealth benchmark</h1>",
        f"<p>{plan['flights']} flights per detector and attacker, attacked from {plan['onset']:g} s to the end; "
        f"the fix moved at most {plan['rate']:g} m/s (black box: accelerating at {plan['accel']:g} m/s^2). "
        "Deviation: the vehicle's horizontal estimation error, the largest reached before the detector's first "
        f"alarm (shipped threshold). Bound: {results['bound_z']:g} standard deviations of GPS against the "
        "sensors' GPS-free evidence after that time.</p>",
        _curves(results),
        "<h2>Deviation unseen (m, median / worst over flights)</h2>", table(stealth_table(results), index=False),
        "<h2>Flights</h2>", table(flights, index=False),
        f"<p>command: <code>{html.escape(str(results.get('provenance', {}).get('command', '')))}</code></p>",
        versions(results.get("versions")),
    ]
    return atomic_write_text(path, page("quadformer stealth benchmark", parts))
