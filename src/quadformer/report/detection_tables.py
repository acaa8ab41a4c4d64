"""The detection benchmark's tables from a results dict: precision, recall and F1 in the paper's
layout (as Markdown and LaTeX too), every metric, ablations, attack typing, recall per attack
type and the stress evaluation."""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from quadformer.detectors.attack_types import ShapeTyper

NOISES = ("exponential", "laplace")
ATTACKS = ("bias", "ramp")
ATTACK_TITLE = {"bias": "Attack I (bias)", "ramp": "Attack II (ramp)", "mix": "Attack mix (mixed)"}


def _grid_axes(results: dict[str, Any]) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The noise shapes and attacks of a profile run's configurations, in the paper's order."""
    noises = tuple(dict.fromkeys(c["noise"] for c in results["configs"]))
    attacks = tuple(dict.fromkeys(c["attack"] for c in results["configs"]))
    order = {k: i for i, k in enumerate(("exponential", "laplace", "gaussian", "bias", "ramp", "mix"))}
    return (tuple(sorted(noises, key=lambda k: order.get(k, 99))),
            tuple(sorted(attacks, key=lambda k: order.get(k, 99))))


def _title(attack: str) -> str:
    return ATTACK_TITLE.get(attack, f"Attack {attack} ({attack})")


def dataset_table(results: dict[str, Any]) -> pd.DataFrame:
    """Rows are methods; columns dataset x P/R/F1 (runs on given datasets)."""
    cols = pd.MultiIndex.from_tuples([(c["name"], m) for c in results["configs"] for m in ("P", "R", "F1")])
    rows = [[v for c in results["configs"] for v in (
        (c["methods"][m]["precision"], c["methods"][m]["recall"], c["methods"][m]["f1"])
        if m in c["methods"] else (np.nan,) * 3)] for m in results["methods_run"]]
    return pd.DataFrame(rows, index=list(results["methods_run"]), columns=cols)


def paper_tables(results: dict[str, Any]) -> dict[str, pd.DataFrame]:
    """One table per model: rows are methods; columns noise x attack x P/R/F1 (profile runs;
    none for runs on given datasets)."""
    tables = {}
    if results.get("profile") is None:
        return tables
    methods = results["methods_run"]
    noises, attacks = _grid_axes(results)
    for model in ("I", "II"):
        if not any(c["model"] == model for c in results["configs"]):
            continue
        cols = pd.MultiIndex.from_tuples([(n, _title(a), m) for n in noises for a in attacks
                                          for m in ("P", "R", "F1")])
        rows = []
        for method in methods:
            row = []
            for n in noises:
                for a in attacks:
                    c = _find(results, model, n, a)
                    r = c["methods"].get(method) if c else None
                    row += [r["precision"], r["recall"], r["f1"]] if r else [np.nan] * 3
            rows.append(row)
        tables[f"model_{model}"] = pd.DataFrame(rows, index=list(methods), columns=cols)
    return tables


def _find(results, model, noise, attack):
    for c in results["configs"]:
        if (c["model"], c["noise"], c["attack"]) == (model, noise, attack):
            return c
    return None


def to_markdown(df: pd.DataFrame) -> str:
    head = ["method"] + [f"{n[:3]} {a.split()[1]} {m}" for n, a, m in df.columns]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for idx, row in df.iterrows():
        lines.append("| " + " | ".join([str(idx)] + [_f(v) for v in row]) + " |")
    return "\n".join(lines) + "\n"


def to_latex(df: pd.DataFrame, model: str) -> str:
    n = len(df.columns)
    noises = tuple(dict.fromkeys(nz for nz, _, _ in df.columns))
    titles = tuple(dict.fromkeys(a for _, a, _ in df.columns))
    out = [r"\begin{tabular}{l" + "c" * n + "}", r"\toprule",
           r"Model " + model + " & " + " & ".join(rf"\multicolumn{{{3 * len(titles)}}}{{c}}{{{nz.capitalize()} noise}}"
                                                 for nz in noises) + r" \\",
           " & " + " & ".join(rf"\multicolumn{{3}}{{c}}{{{a}}}" for _ in noises
                              for a in titles) + r" \\",
           "Method & " + " & ".join(m for _, _, m in df.columns) + r" \\", r"\midrule"]
    for idx, row in df.iterrows():
        out.append(str(idx).replace("_", r"\_") + " & " + " & ".join(_f(v) for v in row) + r" \\")
    out += [r"\bottomrule", r"\end{tabular}"]
    return "\n".join(out) + "\n"


def _f(v: Any) -> str:
    return "-" if v is None or (isinstance(v, float) and not np.isfinite(v)) else f"{v:.2f}"


def extra_table(results: dict[str, Any]) -> pd.DataFrame:
    rows = []
    for c in results["configs"]:
        for m, r in c["methods"].items():
            rows.append({
                "config": c["name"], "method": m, "F1": r["f1"], "event F1": r["event_f1"],
                "delay med (s)": r["delay_median_s"], "delay p95 (s)": r["delay_p95_s"],
                "FA/h (clean)": r["false_alarms_per_hour"], "AUROC": r["auroc"], "AUPRC": r["auprc"],
                "VUS-PR": r.get("vus_pr"),
                "F1 95% CI low": (r.get("f1_ci95") or [None, None])[0],
                "F1 95% CI high": (r.get("f1_ci95") or [None, None])[1],
                "offset at det. (m)": r["offset_at_detection_median_m"],
                "F1 @budget": r["budget"]["f1"], "FA/h @budget": r["budget"]["false_alarms_per_hour"],
                "F1 point-adjusted (inflated)": r["f1_point_adjusted"],
                "onset error med (s)": r.get("onset_error_median_s"),
            })
    df = pd.DataFrame(rows)
    for col in df.columns[2:]:
        df[col] = pd.to_numeric(df[col])     # missing values (None) -> NaN, shown as "-"
    return df


def ablation_table(results: dict[str, Any]) -> pd.DataFrame | None:
    names = [m for m in results["methods_run"] if m.startswith("quadformer")]
    if len(names) < 2:
        return None
    df = pd.DataFrame({c["name"]: {m: c["methods"][m]["f1"] for m in names} for c in results["configs"]})
    df["mean"] = df.mean(axis=1)
    return df


#: the attack-type confusions a run records per method (``experiments.detection.onset_and_types``)
TYPE_CONFUSIONS = {
    "type_confusion": "its own type at the first alarm",
    "type_confusion_shape": "shape typer at the first alarm",
    "type_confusion_shape_confirmed": f"shape typer, confirmed {ShapeTyper.confirm_s:g} s after the first alarm",
}


def confusion_table(results: dict[str, Any], method: str, key: str = "type_confusion") -> pd.DataFrame | None:
    """Counts of true (rows) against predicted (columns) attack types at alarm runs, pooled over
    the configurations; ``key``: one of ``TYPE_CONFUSIONS``."""
    total: dict[str, dict[str, int]] = {}
    found = False
    for c in results["configs"]:
        conf = c["methods"].get(method, {}).get(key)
        if conf is None:
            continue
        found = True
        for t, row in conf.items():
            for p, n in row.items():
                total.setdefault(t, {}).setdefault(p, 0)
                total[t][p] += n
    if not found:
        return None
    return pd.DataFrame(total).T.fillna(0).astype(int)


#: the typings ``attack_typing`` counts per detected attack, and what the report calls them
TYPINGS_COUNTED = {
    "own": "own type at the first alarm",
    "shape_first": "shape typer at the first alarm",
    "shape_confirmed": f"shape typer, confirmed {ShapeTyper.confirm_s:g} s later",
}


def typing_table(results: dict[str, Any]) -> pd.DataFrame | None:
    """Share of detected attacks typed right: rows methods, columns the typings of
    ``TYPINGS_COUNTED`` (a detector that does not classify has no own-type cell), cells
    "share (right/detected attacks)" pooled over the configurations; None when nothing was typed."""
    rows = {}
    for m in results["methods_run"]:
        acc: dict[str, list[int]] = {}
        for c in results["configs"]:
            for key, v in (c["methods"].get(m, {}).get("attack_typing") or {}).items():
                if v is not None:
                    a = acc.setdefault(key, [0, 0])
                    a[0] += v["right"]
                    a[1] += v["attacks"]
        if acc:
            rows[m] = {TYPINGS_COUNTED[k]: _ratio(a) for k, a in acc.items()}
    if not rows:
        return None
    cols = [w for w in TYPINGS_COUNTED.values() if any(w in r for r in rows.values())]
    return pd.DataFrame(rows).T.reindex(columns=cols).fillna("-")


def type_recall_table(results: dict[str, Any]) -> pd.DataFrame | None:
    """Event recall per true attack type: rows methods, columns types, cells "found/windows"
    pooled over the test flights of every configuration (None when no run recorded it)."""
    counts: dict[str, dict[str, list[int]]] = {}
    for c in results["configs"]:
        for m, r in c["methods"].items():
            for t, row in (r.get("event_recall_by_type") or {}).items():
                acc = counts.setdefault(m, {}).setdefault(t, [0, 0])
                acc[0] += row["found"]
                acc[1] += row["windows"]
    if not counts:
        return None
    types = sorted({t for per in counts.values() for t in per})
    rows = {m: {t: _ratio(per.get(t)) for t in types} for m, per in counts.items()}
    return pd.DataFrame(rows).T.reindex([m for m in results["methods_run"] if m in rows])


def _ratio(acc: list[int] | None) -> str:
    if not acc or not acc[1]:
        return "-"
    return f"{acc[0] / acc[1]:.2f} ({acc[0]}/{acc[1]})"


STRESS_COLUMNS = {"event_recall": "event recall", "windows": "attack windows", "delay_median_s": "delay median (s)",
                  "false_alarms_per_hour": "FA/h (clean flights)", "clean_flight_hours": "clean flight-hours",
                  "f1": "F1 (point-wise)", "vus_pr": "VUS-PR"}
#: the same at the false-alarm budget threshold
STRESS_BUDGET_COLUMNS = {"event_recall": "budget: event recall", "delay_median_s": "budget: delay median (s)",
                         "false_alarms_per_hour": "budget: FA/h (clean flights)", "f1": "budget: F1 (point-wise)"}


def stress_table(results: dict[str, Any]) -> pd.DataFrame | None:
    """Per stress set and method, pooled over the configurations it scores: event recall,
    median detection delay, false alarms per flight-hour on the clean stress flights, point-wise
    F1 (and VUS-PR), at the F1 threshold and at the false-alarm budget threshold (``budget:``
    columns). None without a stress evaluation."""
    st = results.get("stress")
    if not st:
        return None
    rows = []
    for set_name in st["sets"]:
        for m in results["methods_run"]:
            r = st["pooled"].get(set_name, {}).get(m)
            if r is None:
                continue
            budget = r.get("budget") or {}
            rows.append({"stress set": set_name, "method": m, "configs": r["configs"],
                         **{title: r.get(k) for k, title in STRESS_COLUMNS.items()},
                         **{title: budget.get(k) for k, title in STRESS_BUDGET_COLUMNS.items()}})
    df = pd.DataFrame(rows)
    for col in df.columns[2:]:
        df[col] = pd.to_numeric(df[col])
    return df
