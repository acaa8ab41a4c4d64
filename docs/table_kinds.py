"""The kinds of table ``docs/tables.py`` generates from a run's ``results.json``: each a function
(results, the table's declaration, its name) -> Markdown, in ``KINDS``.

Kinds (``kind``), and what they read:

- ``methods``: a detection run (``benchmark``): one row per method, one column per
  configuration (Model, noise, attack, in the paper's order); ``metric`` is a key of a method's
  results (dotted for nested ones: ``budget.event_recall``), ``paren`` an optional second one
  shown in brackets.
- ``seeds``: a several-seed run (``benchmark --seeds``): the same layout, ``mean ± std`` of
  ``metric`` over the seeds.
- ``stress``: the stress sets of a ``benchmark --stress`` run, pooled over configurations: one
  row per set, one column per method, event recall / median delay / false alarms per clean
  flight-hour at the false-alarm budget threshold (``at: "budget"``) or the F1 threshold
  (``at: "f1"``).
- ``typing``: per method, the share of detected attacks typed right (own classifier at the
  first alarm; shape typer at the first alarm and confirmed later), pooled over configurations.
- ``resilience``: a ``resilience`` run: one row per policy over every configuration's flights.
- ``zoo``: the shipped detectors' ``index.json`` (``quadformer zoo build``): one row per
  detector, its figures on the zoo's own held-out simulated test flights at both thresholds.
- ``zoo-configs``: one shipped set's (``set``) detectors, test F1 by configuration.
- ``field``: a ``benchmark --profile field`` run: per method and threshold (the simulation's,
  calibrated on the other clean logs), spoofing alerts in the air per in-air hour on the clean
  flights with the exposure and the Poisson interval, the alerts counted apart, and the injected
  spoofs' event recall, recall on the targets' sizes and median delay.

The stealth benchmark's kinds are in ``docs/table_kinds_stealth.py``.

Options common to every kind: ``methods`` (a subset of methods, in this order; default every
method of the run), ``digits`` (default 2). Only the standard library is needed, except for
``resilience`` tables, which summarise flights with ``quadformer.evaluation.resilience``.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]

NOISE = {"exponential": "exp", "laplace": "lap", "gaussian": "gauss"}
ORDER = {k: i for i, k in enumerate(("I", "II", "exponential", "laplace", "gaussian", "bias", "ramp", "mix"))}
CONFIG_NAME = re.compile(r"model(?P<model>I{1,2})-(?P<noise>[a-z]+)-(?P<attack>[a-z]+)$")


class TableError(Exception):
    """A declared table that cannot be generated (missing source, unknown kind or method)."""


# ---------------------------------------------------------------------------------------------
# formatting


def fmt(v: Any, digits: int = 2) -> str:
    if v is None or (isinstance(v, float) and v != v):
        return "-"
    if isinstance(v, bool):
        return str(v)
    if isinstance(v, int):
        return str(v)
    return f"{v:.{digits}f}"


def as_float(v: Any) -> float | None:
    """A metric as a float (JSON may hold 0 or 1 as integers); None stays None."""
    return None if v is None else float(v)


def markdown(head: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def get(d: dict[str, Any] | None, key: str) -> Any:
    """``d[key]``, dotted keys reaching into nested dicts; None where absent."""
    for part in key.split("."):
        if not isinstance(d, dict):
            return None
        d = d.get(part)
    return d


# ---------------------------------------------------------------------------------------------
# configurations and methods


def config_key(c: dict[str, Any]) -> tuple:
    """Sort key of a configuration: Model, noise, attack in the paper's order; else its name."""
    parts = [c.get("model"), c.get("noise"), c.get("attack")]
    if None in parts:
        m = CONFIG_NAME.match(c["name"])
        if not m:
            return (99, c["name"])
        parts = [m["model"], m["noise"], m["attack"]]
    return tuple(ORDER.get(p, 50) for p in parts) + (c["name"],)


def config_label(c: dict[str, Any]) -> str:
    """``I exp bias`` for a profile's configuration, its name otherwise."""
    m = CONFIG_NAME.match(c["name"])
    if not m:
        return c["name"]
    return f"{m['model']} {NOISE.get(m['noise'], m['noise'])} {m['attack']}"


def pick_methods(available: list[str], wanted: list[str] | None, name: str) -> list[str]:
    if wanted is None:
        return list(available)
    missing = [m for m in wanted if m not in available]
    if missing:
        raise TableError(f"table {name!r}: method(s) {', '.join(missing)} not in the run "
                         f"(it has {', '.join(available)})")
    return list(wanted)


# ---------------------------------------------------------------------------------------------
# the kinds of table


def table_methods(res: dict[str, Any], spec: dict[str, Any], name: str) -> str:
    if "configs" not in res or "methods_run" not in res:
        raise TableError(f"table {name!r}: not a detection run's results.json (no configs / methods_run)")
    configs = sorted(res["configs"], key=config_key)
    methods = pick_methods(res["methods_run"], spec.get("methods"), name)
    key, paren, digits = spec.get("metric", "f1"), spec.get("paren"), spec.get("digits", 2)
    rows = []
    for m in methods:
        row = [m]
        for c in configs:
            r = c["methods"].get(m)
            cell = fmt(as_float(get(r, key)), digits)
            if paren:
                cell += f" ({fmt(as_float(get(r, paren)), digits)})"
            row.append(cell)
        rows.append(row)
    return markdown(["method", *(config_label(c) for c in configs)], rows)


def table_seeds(res: dict[str, Any], spec: dict[str, Any], name: str) -> str:
    if "summary" not in res or "seeds" not in res:
        raise TableError(f"table {name!r}: not a several-seed run's results.json (no summary / seeds)")
    configs = sorted(({"name": n} for n in res["summary"]), key=config_key)
    methods = pick_methods(res["methods_run"], spec.get("methods"), name)
    metric, digits = spec.get("metric", "f1"), spec.get("digits", 2)
    rows = []
    for m in methods:
        row = [m]
        for c in configs:
            s = get(res["summary"][c["name"]], f"{m}.{metric}")
            if s is None:
                row.append("-")
            elif s.get("std") is None:
                row.append(fmt(s["mean"], digits))
            else:
                row.append(f"{fmt(s['mean'], digits)} ± {fmt(s['std'], digits)}")
        rows.append(row)
    return markdown(["method", *(config_label(c) for c in configs)], rows)


def table_stress(res: dict[str, Any], spec: dict[str, Any], name: str) -> str:
    pooled = get(res, "stress.pooled")
    if not pooled:
        raise TableError(f"table {name!r}: the run has no stress results (benchmark --stress)")
    methods = pick_methods(res["methods_run"], spec.get("methods"), name)
    at, digits = spec.get("at", "budget"), spec.get("digits", 2)
    order = list(get(res, "stress.sets") or {})
    sets = sorted(pooled, key=lambda s: order.index(s) if s in order else len(order))
    rows = []
    for st in sets:
        row = [st]
        for m in methods:
            r = pooled[st].get(m)
            if at == "budget":
                r = get(r, "budget")
            if r is None:
                row.append("-")
                continue
            delay = r.get("delay_median_s")
            row.append(f"{fmt(as_float(r.get('event_recall')), digits)} / "
                       f"{'-' if delay is None else fmt(float(delay), 1) + ' s'} / "
                       f"{fmt(as_float(r.get('false_alarms_per_hour')), 1)}")
        rows.append(row)
    return markdown(["stress set", *methods], rows)


def table_typing(res: dict[str, Any], spec: dict[str, Any], name: str) -> str:
    if "configs" not in res:
        raise TableError(f"table {name!r}: not a detection run's results.json (no configs)")
    methods = pick_methods(res["methods_run"], spec.get("methods"), name)
    digits = spec.get("digits", 2)
    cols = (("own", "own classifier, first alarm"), ("shape_first", "shape typer, first alarm"),
            ("shape_confirmed", "shape typer, confirmed"))
    rows = []
    for m in methods:
        row = [m]
        for key, _ in cols:
            counts = [get(c["methods"].get(m), f"attack_typing.{key}") for c in res["configs"]]
            counts = [n for n in counts if n is not None]
            if not counts:
                row.append("-")
                continue
            right, n = sum(x["right"] for x in counts), sum(x["attacks"] for x in counts)
            row.append(f"{fmt(right / n, digits) if n else '-'} ({right}/{n})")
        rows.append(row)
    return markdown(["method", *(title for _, title in cols)], rows)


def table_resilience(res: dict[str, Any], spec: dict[str, Any], name: str) -> str:
    if "policies" not in res or "configs" not in res:
        raise TableError(f"table {name!r}: not a resilience run's results.json (no policies / configs)")
    try:
        from quadformer.evaluation.resilience import summarize_policy
    except ImportError:                   # run from a checkout without the package installed
        sys.path.insert(0, str(ROOT / "src"))
        from quadformer.evaluation.resilience import summarize_policy

    digits = spec.get("digits", 2)
    d = lambda v: fmt(v, digits)           # noqa: E731
    rows = []
    for p in spec.get("policies", res["policies"]):
        flights = [r for c in res["configs"] for r in c["flights"] if r["policy"] == p]
        s = summarize_policy(flights)
        share = s["wrongly_excluded_fraction"]
        excl = (f"{d(s['exclusion_precision'])} / {d(s['exclusion_recall'])} / {d(s['exclusion_f1'])}"
                if p != "naive" else "-")
        rows.append([p, str(s["attacked_flights"]),
                     f"{d(s['max_dev_median_m'])} / {d(s['max_dev_p95_m'])} / {d(s['max_dev_max_m'])}",
                     d(s["est_err_rms_median_m"]), fmt(s["exclusion_delay_median_s"], 1),
                     f"{fmt(s['readmit_delay_median_s'], 1)} / {fmt(s['readmit_delay_p95_s'], 1)}",
                     str(s["not_readmitted"]), str(s["stale_readmissions"]),
                     "-" if share is None else f"{100 * share:.1f}%", excl])
    head = ["policy", "attacked flights", "max deviation from mission during attack, median / p95 / worst (m)",
            "estimate error RMS, median (m)", "onset to exclusion, median (s)",
            "end to re-admission, median / p95 (s)", "never re-admitted", "stale re-admissions",
            "GPS wrongly excluded (clean time)", "exclusion P / R / F1"]
    return markdown(head, rows)


FIELD_KINDS = {"bias": ("bias", "2 m"), "capture": ("capture", "2 m"), "ramp": ("ramp", "0.2 m/s"),
               "drift": ("drift switched on at once", "0.2 m/s"), "drift-accel": ("accelerating drift", "0.2 m/s")}


def table_field(res: dict[str, Any], spec: dict[str, Any], name: str) -> str:
    if "false_alarms" not in res or "injection" not in res:
        raise TableError(f"table {name!r}: not a field run's results.json (no false_alarms / injection)")
    fa = {(r["method"], r["threshold"]): r for r in res["false_alarms"]}
    inj = {(r["method"], r["threshold"], r["kind"]): r for r in res["injection"]}
    methods = pick_methods(list(dict.fromkeys(r["method"] for r in res["false_alarms"])), spec.get("methods"), name)
    kinds = [k for k in spec.get("kinds", ("bias", "ramp")) if any(r["kind"] == k for r in res["injection"])]
    floor = any("recall_floor" in r for r in res["injection"])
    tail = any("recall_tail" in r for r in res["injection"])
    settled = any("recall_settled" in r for r in res["injection"])
    digits = spec.get("digits", 2)
    rows = []
    for m in methods:
        for thr in ("sim", "calibrated"):
            f = fa.get((m, thr))
            if f is None:
                continue
            cells = [m, thr, f"{f['spoofing_air']} in {f['air_hours']:.3f} h: {fmt(f['per_air_hour'], 0)} "
                             f"[{fmt(f['ci_low'], 0)}, {fmt(f['ci_high'], 0)}]",
                     f"{f['ground']} / {f['transition']} / {f['degraded']}"]
            for kind in kinds:
                r = inj.get((m, thr, kind))
                if r is None:
                    cells.append("-")
                    continue
                parts = [fmt(r["event_recall"], digits), fmt(r["recall_big"], digits)]
                if floor:
                    n = as_float(r.get("floor_injected"))
                    parts.append("-" if not n or n != n else f"{fmt(r.get('recall_floor'), digits)} ({int(n)})")
                if tail:
                    n = as_float(r.get("tail_injected"))
                    parts.append("-" if not n or n != n else f"{fmt(r.get('recall_tail'), digits)} ({int(n)})")
                if settled:
                    n = as_float(r.get("settled_injected"))
                    parts.append("-" if not n or n != n else f"{fmt(r.get('recall_settled'), digits)} ({int(n)})")
                delay = fmt(r["delay_median_s"], 1)
                parts.append(delay + (" s" if delay != "-" else ""))
                cells.append(" / ".join(parts))
            rows.append(cells)
    head = ["method", "threshold", "spoofing alerts in air on clean flights: count in in-air hours, per hour [95%]",
            "ground / transition / degraded alerts"]
    for kind in kinds:
        what, target = FIELD_KINDS.get(kind, (kind, "the target"))
        head.append(f"injected {what}: recall / recall >= {target} / "
                    + ("recall at or above the target and the log's floor (spoofs) / " if floor else "")
                    + ("the same at the floor with the log's tails (spoofs) / " if tail else "")
                    + ("recall of those begun after 30 s in the air (spoofs) / " if settled else "")
                    + "median delay")
    return markdown(head, rows)


def _tail(value: Any, dof: Any, unit: str) -> str:
    v, d = as_float(value), as_float(dof)
    if v is None or v != v:
        return "-"
    return f"{v:.2f} {unit} ({'Gaussian' if d == float('inf') else fmt(d, 1)})"


def table_floors(res: dict[str, Any], spec: dict[str, Any], name: str) -> str:
    floors = res.get("floors")
    if not floors:
        raise TableError(f"table {name!r}: the field run has no physical floors (run it again)")
    rows = []
    tails = any("offset_tail_m" in f for f in floors.values())
    for log, f in floors.items():
        if "reason" in f:
            rows.append([log, f["vehicle"], "-", "-", *(["-", "-"] if tails else []), f["reason"]])
            continue
        with_tails = [_tail(f.get("offset_tail_m"), f.get("tail_dof_pos"), "m"),
                      _tail(f.get("drift_tail_ms"), f.get("tail_dof_vel"), "m/s")] if tails else []
        rows.append([log, f["vehicle"], f"{f['offset_m']:.2f} m ({f['sigma_pos_m']:.3f} m)",
                     f"{f['drift_ms']:.2f} m/s ({f['sigma_vel_ms']:.3f} m/s)", *with_tails,
                     f"{f['intervals']} intervals at {f['gps_rate_hz']:.1f} Hz"])
    head = ["clean log", "vehicle", "offset floor (robust std of one interval's position step)",
            "drift floor (robust std of one interval's velocity step against the IMU)",
            *(["offset floor with the log's tails (Student-t dof)", "drift floor with the log's tails (Student-t dof)"]
              if tails else []), "on"]
    return markdown(head, rows)


def table_zoo(res: dict[str, Any], spec: dict[str, Any], name: str) -> str:
    """The shipped detectors (the package's ``index.json``): one row per detector, its figures on
    the zoo's held-out simulated test flights at both thresholds."""
    d = spec.get("digits", 2)
    rows = []
    for det_name, e in res["detectors"].items():
        s = res["sets"][e["set"]]
        c = e["card"]
        f, b = c["test"]["at_f1_threshold"], c["test"]["at_budget_threshold"]
        ci = f.get("f1_ci95")
        flights = sum(x["flights"] for x in c["training"]["simulation"])
        rows.append([f"`{det_name}`" + (" (default)" if s["default"] == det_name else ""), e["method"],
                     f"{s['sensors']}, {s['residues']}", str(flights),
                     f"{fmt(f['f1'], d)} [{fmt(ci[0], d)}, {fmt(ci[1], d)}]" if ci else fmt(f["f1"], d),
                     fmt(b["f1"], d), fmt(b["event_recall"], d), fmt(b["delay_median_s"], 1),
                     fmt(b["false_alarms_per_hour"], 1)])
    head = ["detector", "method", "sensors, residues", "simulated flights (60/20/20)", "test F1 [95%]",
            "budget: F1", "budget: event recall", "budget: median delay (s)", "budget: FA/h (clean)"]
    return markdown(head, rows)


def table_zoo_configs(res: dict[str, Any], spec: dict[str, Any], name: str) -> str:
    """One shipped set's detectors (``set``) by configuration: test F1 at the F1 threshold."""
    d = spec.get("digits", 2)
    dets = {k: e for k, e in res["detectors"].items() if e["set"] == spec["set"]}
    if not dets:
        raise TableError(f"table {name!r}: no shipped detector of set {spec['set']!r}")
    first = next(iter(dets.values()))["card"]["test"]["at_f1_threshold"]["per_config_f1"]
    configs = sorted(first, key=lambda n: config_key({"name": n}))
    rows = [[e["method"]] + [fmt(e["card"]["test"]["at_f1_threshold"]["per_config_f1"].get(c), d) for c in configs]
            for e in dets.values()]
    return markdown(["method"] + [config_label({"name": c}) for c in configs], rows)


KINDS = {"methods": table_methods, "seeds": table_seeds, "stress": table_stress, "typing": table_typing,
         "resilience": table_resilience, "field": table_field, "floors": table_floors, "zoo": table_zoo,
         "zoo-configs": table_zoo_configs}
