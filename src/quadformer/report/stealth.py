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


def plan_name(accel: float | None) -> str:
    """A white or grey box's plan as the tables and the output name it (None: no plan)."""
    return "fastest push" if accel is None else f"plan {accel:g} m/s^2"


def attacker(run: dict[str, Any]) -> str:
    """A run's attacker as the tables name it: its knowledge, the white box's margin, the axes it
    searched where more than one, and the plan it rehearsed and flew where it rehearsed."""
    plan = run.get("rehearsal")
    return (run["knowledge"] + (f" {run['margin']:g}" if run["margin"] else "")
            + (f", {run['headings']} headings" if run.get("headings", 1) > 1 else "")
            + ("" if plan is None else f", rehearsed: {plan_name(plan['accel'])}"))


def runs_under(results: dict[str, Any], policy: str) -> list[dict[str, Any]]:
    """The runs flown under the GPS policy ``policy`` (results written before the policies: every
    run under none, GPS always fused)."""
    return [r for r in results["runs"] if r.get("policy", "none") == policy]


def unguarded(results: dict[str, Any]) -> list[dict[str, Any]]:
    """The runs flown with GPS always fused."""
    return runs_under(results, "none")


def _frame(results: dict[str, Any], runs: list[dict[str, Any]], measure: str, first: dict, middle: dict
           ) -> pd.DataFrame:
    """One row per run: its detector and attacker, the ``first`` columns, the median and worst
    ``measure`` (``deviation`` or ``reached``) by each horizon, the ``middle`` columns, the bound
    and the worst at the last horizon as a ratio to it (``first``, ``middle``: {heading: run ->
    cell})."""
    horizons = tuple(results["plan"]["horizons"])
    last = f"{max(horizons):g}"
    rows = []
    for r in runs:
        s, b = r["summary"], results["bounds"][r["set"]]
        row = {"detector": r["detector"], "attacker": attacker(r), **{k: f(r) for k, f in first.items()}}
        for T in horizons:
            row[f"{T:g} s"] = f"{s[f'{measure}_median_{T:g}']:.1f} / {s[f'{measure}_worst_{T:g}']:.1f}"
        row.update({k: f(r) for k, f in middle.items()})
        row[f"bound {last} s"] = f"{b[last]:.1f}"
        row["worst / bound"] = f"{s[f'{measure}_worst_{last}'] / b[last]:.1f}"
        rows.append(row)
    return pd.DataFrame(rows)


def stealth_table(results: dict[str, Any]) -> pd.DataFrame:
    """One row per detector, knowledge and margin flown with GPS always fused: the median and worst
    deviation unseen by each horizon, the share of flights still hidden at the last, the bound and
    the ratio to it."""
    last = f"{max(results['plan']['horizons']):g}"
    own = {"threshold (attacker's)": lambda r: f"{r['threshold']:.4g}"
           + (f" ({r['surrogate']['threshold']:.4g})" if r.get("surrogate") else "")}
    return _frame(results, unguarded(results), "deviation", own,
                  {f"hidden at {last} s": lambda r: f"{r['summary'][f'hidden_{last}']:.0%}"})


def resilient_table(results: dict[str, Any]) -> pd.DataFrame:
    """One row per detector, knowledge and margin flown under the resilient GPS policy, its alarms
    in the loop: the median and worst deviation reached by each horizon (alarm or not: what the
    attack achieves with the defence acting), the flights that alarmed, the share of fixes fused
    after the onset, the bound and the worst as a ratio to it."""
    return _frame(results, runs_under(results, "resilient"), "reached", {},
                  {"alarmed": lambda r: f"{r['summary']['alarmed']} of {r['summary']['flights']}",
                   "GPS fused after the onset": lambda r: f"{r['summary']['fused_after_onset']:.0%}"})


def _curves(results: dict[str, Any]) -> str:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    horizons = [float(h) for h in results["plan"]["horizons"]]
    runs = unguarded(results)
    panels = sorted({(r["set"], attacker(r)) for r in runs})
    if not panels:                  # every run under the resilient policy: its table says it
        return ""
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
    flights = pd.DataFrame([{"detector": r["detector"], "attacker": attacker(r), "policy": r.get("policy", "none"), **f}
                            for r in results["runs"] for f in r["flights"]])
    parts = [
        "<h1>quadformer stealth benchmark</h1>",
        f"<p>{plan['flights']} flights per detector and attacker, attacked from {plan['onset']:g} s to the end; "
        f"the fix moved at most {plan['rate']:g} m/s (black box: accelerating at {plan['accel']:g} m/s^2). "
        "Deviation: the vehicle's horizontal estimation error, the largest reached before the detector's first "
        f"alarm (shipped threshold). Bound: {results['bound_z']:g} standard deviations of GPS against the "
        "sensors' GPS-free evidence after that time.</p>",
        _curves(results),
        *(["<h2>Deviation unseen (m, median / worst over flights)</h2>", table(stealth_table(results), index=False)]
          if unguarded(results) else []),
        *(["<h2>Under the resilient GPS policy: deviation reached (m, median / worst over flights)</h2>",
           "<p>The detector's alarms drive the resilient policy in the loop (GPS leaves the fusion on an alarm and "
           "comes back once trustworthy); the deviation reached by each horizon, alarm or not.</p>",
           table(resilient_table(results), index=False)]
          if runs_under(results, "resilient") else []),
        "<p>Threshold: the vehicle's detector's; in brackets the grey box's own, of the surrogate it fitted on "
        "its own flights.</p>" + "".join(f"<p>Not run: {html.escape(n['detector'])}, {html.escape(n['knowledge'])} "
                                          f"box ({html.escape(n['reason'])}).</p>" for n in results.get("not_run", [])),
        "<h2>Flights</h2>", table(flights, index=False),
        f"<p>command: <code>{html.escape(str(results.get('provenance', {}).get('command', '')))}</code></p>",
        versions(results.get("versions")),
    ]
    return atomic_write_text(path, page("quadformer stealth benchmark", parts))
