"""The stealth benchmark's kinds of table for ``docs/tables.py`` (``benchmark --profile stealth``;
the other kinds and the helpers are in ``docs/table_kinds.py``):

- ``stealth``: per shipped detector and attacker, the deviation unseen by each horizon, the
  flights still hidden at the last, the worst as a ratio to the physical bound;
- ``stealth-summary``: the same at one ``horizon`` (s), the farthest attacker per detector;
- ``stealth-resilient``: the runs under the resilient GPS policy, the deviation reached by each
  horizon alarm or not, the flights alarmed and the fixes fused after the onset.

Each reads the runs flown under the GPS policy ``policy`` (default none; ``stealth-resilient``:
resilient) of the detectors ``methods`` names (default every one).
"""

from __future__ import annotations

from typing import Any

from table_kinds import TableError, markdown, pick_methods

from quadformer.report.stealth import plan_name


def _attacker(run: dict[str, Any]) -> str:
    """A stealth run's attacker: its knowledge, the white and grey box's margin, the plan it
    rehearsed and flew, and the threshold of the grey box's own surrogate."""
    own, plan = run.get("surrogate"), run.get("rehearsal")
    return (run["knowledge"] + (f" {run['margin']:g}" if run["margin"] else "")
            + (f", {run['headings']} headings" if run.get("headings", 1) > 1 else "")
            + ("" if plan is None else f", rehearsed: {plan_name(plan['accel'])}")
            + (f" (own threshold {own['threshold']:.3g}, the vehicle's {run['threshold']:.3g})" if own else ""))


def stealth_runs(res: dict[str, Any], spec: dict[str, Any], name: str) -> list[dict[str, Any]]:
    """A stealth benchmark's runs, of the detectors ``methods`` names (default every one), flown
    under the GPS policy ``policy`` (default none: GPS always fused)."""
    runs, bounds = res.get("runs"), res.get("bounds")
    if not runs or not bounds:
        raise TableError(f"table {name!r}: not a stealth benchmark's results (no runs or bounds)")
    keep = pick_methods(list(dict.fromkeys(r["detector"] for r in runs)), spec.get("methods"), name)
    policy = spec.get("policy", "none")
    out = [r for r in runs if r["detector"] in keep and r.get("policy", "none") == policy]
    if not out:
        raise TableError(f"table {name!r}: no run under the GPS policy {policy!r} in the results")
    return out


def _envelope(res: dict[str, Any], runs: list[dict[str, Any]], measure: str, label: str,
              middle: dict[str, Any]) -> str:
    """Per set a row of its physical bound, then per run its detector and attacker, the median /
    worst ``measure`` (``deviation`` or ``reached``) by each horizon, the ``middle`` columns
    ({heading: summary -> cell}) and the worst at the last horizon as a ratio to the bound."""
    bounds = res["bounds"]
    horizons = [f"{float(h):g}" for h in res["plan"]["horizons"]]
    last = horizons[-1]
    rows = []
    for set_name in dict.fromkeys(r["set"] for r in runs):
        b = bounds[set_name]
        rows.append([f"**{set_name}: physical bound**", "-", *[f"{b[h]:.1f}" for h in horizons],
                     *["-"] * len(middle), "1"])
        for r in (r for r in runs if r["set"] == set_name):
            s = r["summary"]
            rows.append([f"`{r['detector']}`", _attacker(r),
                         *[f"{s[f'{measure}_median_{h}']:.1f} / {s[f'{measure}_worst_{h}']:.1f}" for h in horizons],
                         *[cell(s) for cell in middle.values()], f"{s[f'{measure}_worst_{last}'] / b[last]:.2f}"])
    head = ["detector", "attacker (margin)", *[f"{label} {h} s (m)" for h in horizons], *middle,
            f"worst / bound at {last} s"]
    return markdown(head, rows)


def table_stealth(res: dict[str, Any], spec: dict[str, Any], name: str) -> str:
    """The stealth benchmark: per shipped detector and attacker, the deviation unseen by each
    horizon (median / worst over flights, m), the flights still hidden at the last horizon, and
    the worst as a ratio to the physical bound; one row per set gives the bound itself."""
    last = f"{float(res['plan']['horizons'][-1]):g}"
    return _envelope(res, stealth_runs(res, spec, name), "deviation", "unseen by",
                     {f"hidden at {last} s": lambda s: f"{s[f'hidden_{last}']:.0%}"})


def table_stealth_summary(res: dict[str, Any], spec: dict[str, Any], name: str) -> str:
    """The stealth benchmark at one horizon (``horizon``, s): per detector, the attacker who went
    farthest unseen (the worst flight), its median / worst deviation unseen, the flights it kept
    hidden, and the worst as a ratio to the physical bound."""
    runs, bounds = stealth_runs(res, spec, name), res["bounds"]
    h = f"{float(spec['horizon']):g}"
    if f"deviation_worst_{h}" not in runs[0]["summary"]:
        raise TableError(f"table {name!r}: no horizon {h} s in the results")
    rows = []
    for det in dict.fromkeys(r["detector"] for r in runs):
        best = max((r for r in runs if r["detector"] == det), key=lambda r: r["summary"][f"deviation_worst_{h}"])
        s, b = best["summary"], bounds[best["set"]][h]
        rows.append([f"`{det}`", _attacker(best),
                     f"{s[f'deviation_median_{h}']:.1f} / {s[f'deviation_worst_{h}']:.1f}",
                     f"{s[f'hidden_{h}']:.0%}", f"{b:.1f}", f"{s[f'deviation_worst_{h}'] / b:.2f}"])
    head = ["detector", "farthest attacker", f"deviation unseen by {h} s, median / worst (m)", f"hidden at {h} s",
            f"physical bound at {h} s (m)", "worst / bound"]
    return markdown(head, rows)


def table_stealth_resilient(res: dict[str, Any], spec: dict[str, Any], name: str) -> str:
    """The stealth benchmark under the resilient GPS policy (the detector's alarms exclude GPS in
    the loop): per detector and attacker, the deviation reached by each horizon, alarm or not
    (median / worst over flights, m), the flights that alarmed, the fixes fused after the onset,
    and the worst as a ratio to the physical bound."""
    return _envelope(res, stealth_runs(res, {**spec, "policy": "resilient"}, name), "reached", "reached by",
                     {"flights alarmed": lambda s: f"{s['alarmed']} of {s['flights']}",
                      "GPS fused after the onset": lambda s: f"{s['fused_after_onset']:.0%}"})


KINDS = {"stealth": table_stealth, "stealth-summary": table_stealth_summary,
         "stealth-resilient": table_stealth_resilient}
