"""The detection benchmark's outputs: tables in the paper's layout (Markdown, CSV, LaTeX),
figures (PNG) and report.html, from a results dict."""

from __future__ import annotations

import html
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from quadformer.dataset import load_dataset
from quadformer.detectors.attack_types import ShapeTyper
from quadformer.evaluation.metrics import flight_events
from quadformer.io import atomic_write_text
from quadformer.report.html import img, page, png, table

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


def _markdown(df: pd.DataFrame) -> str:
    head = ["method"] + [f"{n[:3]} {a.split()[1]} {m}" for n, a, m in df.columns]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for idx, row in df.iterrows():
        lines.append("| " + " | ".join([str(idx)] + [_f(v) for v in row]) + " |")
    return "\n".join(lines) + "\n"


def _latex(df: pd.DataFrame, model: str) -> str:
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


def _figures(results: dict[str, Any], out: Path) -> dict[str, str]:
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


def write_report(results: dict[str, Any], out: Path) -> Path:
    """Write table_model_{I,II}.{md,csv,tex}, metrics.csv, figures/ and report.html into out."""
    out = Path(out)
    tables = paper_tables(results)
    for key, df in tables.items():
        model = key.split("_")[1]
        atomic_write_text(out / f"table_{key}.md", _markdown(df))
        flat = df.copy()
        flat.columns = [f"{n}/{a}/{m}" for n, a, m in df.columns]
        atomic_write_text(out / f"table_{key}.csv", flat.to_csv(index_label="method"))
        atomic_write_text(out / f"table_{key}.tex", _latex(df, model))
    extra = extra_table(results)
    atomic_write_text(out / "metrics.csv", extra.to_csv(index=False))
    figs = _figures(results, out)

    if results.get("profile") is not None:
        head = (f"<h1>quadformer benchmark: profile {html.escape(results['profile'])}</h1>"
                f"<p>{results['flights_per_config']} flights of {results['duration_s']:.0f} s per configuration; ")
    else:
        head = (f"<h1>quadformer benchmark: {len(results['configs'])} dataset(s)</h1><p>datasets: "
                + ", ".join(html.escape(c["dataset"]) for c in results["configs"]) + "; ")
    parts = [head + f"protocol: {html.escape(results['protocol'])}. Labels of "
             f"{results['label_fraction']:.0%} of the training flights are available to every method.</p>"]
    for key, df in tables.items():
        parts.append(f"<h2>Model {key.split('_')[1]}: point-wise precision, recall, F1 (test flights)</h2>")
        parts.append(table(df))
    if not tables:
        df = dataset_table(results)
        flat = df.copy()
        flat.columns = [f"{d}/{m}" for d, m in df.columns]
        atomic_write_text(out / "table_datasets.csv", flat.to_csv(index_label="method"))
        parts.append("<h2>Point-wise precision, recall, F1 (test flights)</h2>")
        parts.append(table(df))
    parts.append("<h2>All metrics</h2><p>Event-wise scores, detection delays, false alarms per hour on clean "
                 "test flights, threshold-free AUROC/AUPRC and VUS-PR (range-based PR area averaged over label "
                 "buffers of 0 to 5 s, Paparrizos et al.), a 95% bootstrap interval of the F1 over test flights, "
                 "scores at the false-alarm budget threshold. "
                 "The point-adjusted F1 is shown only for comparison with the literature: it inflates "
                 "scores and is not the result.</p>")
    parts.append(table(extra, index=False))
    for key, b64 in figs.items():
        parts.append(f"<h3>{html.escape(key)}</h3>{img(b64)}")
    abl = ablation_table(results)
    if abl is not None:
        atomic_write_text(out / "ablation.csv", abl.to_csv())
        parts.append("<h2>QUADFormer ablations: point-wise F1 (test)</h2><p>noprior: a fixed prior (Gaussian "
                     "kernel of width 2 steps, not learned); nosup: no "
                     "supervised terms (no labels); nodisc: no discrepancy term.</p>")
        parts.append(table(abl))
    stress = stress_table(results)
    if stress is not None:
        atomic_write_text(out / "stress.csv", stress.to_csv(index=False))
        st = results["stress"]
        parts.append("<h2>Stress evaluation: attacks outside the tuning ranges</h2>"
                     f"<p>{html.escape(st['protocol'])}. {st['flights_per_set']} flights per stress dataset "
                     "(half attacked), one dataset per set and configuration; a set is pooled over the "
                     "configurations whose detectors it scores (bias-tuned: small offsets, long bias, freeze, "
                     "replay, intermittent; ramp-tuned: slow drifts, long ramp, sinusoid; mix-tuned: all; "
                     "every detector: its own attack under Gaussian noise). False alarms per flight-hour are "
                     "counted on the clean stress flights. Two operating points, both chosen on the main run's "
                     "validation flights: the threshold of best F1 there, and the false-alarm budget threshold "
                     "(<code>budget:</code> columns; at most the budget of alarms per clean validation "
                     "flight-hour).</p>")
        sets = pd.DataFrame([{"stress set": k, "what": v["what"],
                              "scores detectors tuned on": ", ".join(v["scores_detectors_tuned_on"]),
                              "flight (s)": v["flight_s"] or "as the configuration"} for k, v in st["sets"].items()])
        parts.append(table(sets, index=False))
        parts.append(table(stress, index=False))
    recall = type_recall_table(results)
    if recall is not None:
        atomic_write_text(out / "event_recall_by_type.csv", recall.to_csv(index_label="method"))
        parts.append("<h2>Event recall per attack type (test flights)</h2><p>Attack windows holding an alarm "
                     "over the windows of that true type, all configurations pooled: recall (found/windows).</p>")
        parts.append(table(recall))
    typing = typing_table(results)
    if typing is not None:
        atomic_write_text(out / "typing.csv", typing.to_csv(index_label="method"))
        parts.append("<h2>Attack typing at alarms (test flights)</h2><p>Detected attacks (an attacked test "
                     "flight with an alarm on an attacked step), all configurations pooled: the share whose "
                     "type is right (right/detected). Own type: the detector's classifier (trained on the "
                     "labelled share of the training flights), at the first alarm on the attack. Shape "
                     "typer: each attack shape fitted to GPS minus the GPS-free reference, no labels "
                     "(<code>detectors.attack_types</code>), at that first alarm and confirmed "
                     f"{ShapeTyper.confirm_s:g} s later "
                     "(whether or not the alarm still stands). The confusion matrices "
                     "below count every alarm run, false alarms (row none) included.</p>")
        parts.append(table(typing))
    for m in results["methods_run"]:
        for key, what in TYPE_CONFUSIONS.items():
            conf = confusion_table(results, m, key)
            if conf is None or (key == "type_confusion" and set(conf.columns) <= {"attack"}):
                continue
            parts.append(f"<details><summary>{html.escape(m)}: attack types at alarm runs, {what}</summary>"
                         "<p>Rows: true type at the run's first alarm (none: a false alarm); columns: "
                         "predicted type; all test flights of all configurations.</p>" + table(conf) + "</details>")
    parts.append("<h2>Versions</h2><pre>" + html.escape(str(results.get("versions", {}))) + "</pre>")
    doc = page("quadformer report", parts)
    atomic_write_text(out / "report.html", doc)
    return out / "report.html"


# -- several seeds ----------------------------------------------------------------------------

def seeds_table(results: dict[str, Any], metric: str = "f1") -> pd.DataFrame:
    """One metric over the seeds: rows methods, columns configurations, cells
    "mean ± std [min, max]" (``run_seeds``' summary)."""
    summary = results["summary"]
    cols = list(summary)
    rows = {}
    for m in results["methods_run"]:
        rows[m] = {c: _spread(summary[c].get(m, {}).get(metric)) for c in cols}
    return pd.DataFrame(rows).T[cols]


def _spread(v: dict[str, Any] | None) -> str:
    if not v:
        return "-"
    std = "-" if v["std"] is None else f"{v['std']:.2f}"
    return f"{v['mean']:.2f} ± {std} [{v['min']:.2f}, {v['max']:.2f}]"


SEED_TABLES = {"f1": "point-wise F1", "event_f1": "event-wise F1", "vus_pr": "VUS-PR", "auprc": "AUPRC",
               "false_alarms_per_hour": "false alarms per flight-hour (clean test flights)"}


def write_seeds_report(results: dict[str, Any], out: Path) -> Path:
    """``seeds_<metric>.{md,csv}`` and report.html of a several-seed run."""
    out = Path(out)
    parts = [f"<h1>quadformer benchmark over {len(results['seeds'])} seeds: profile "
             f"{html.escape(results['profile'])}</h1><p>{html.escape(results['protocol'])}. Seeds: "
             + ", ".join(str(s) for s in results["seeds"]) + ". Cells: mean ± standard deviation over the seeds "
             "[min, max]. Each seed's own report: "
             + ", ".join(f"<code>{html.escape(r['dir'])}/report.html</code>" for r in results["runs"]) + ".</p>"]
    for metric, title in SEED_TABLES.items():
        df = seeds_table(results, metric)
        atomic_write_text(out / f"seeds_{metric}.csv", df.to_csv(index_label="method"))
        atomic_write_text(out / f"seeds_{metric}.md", _markdown_plain(df))
        parts.append(f"<h2>{html.escape(title)} over seeds (test flights)</h2>")
        parts.append(table(df))
    parts.append("<h2>Versions</h2><pre>" + html.escape(str(results.get("versions", {}))) + "</pre>")
    atomic_write_text(out / "report.html", page("quadformer report over seeds", parts))
    return out / "report.html"


def _markdown_plain(df: pd.DataFrame) -> str:
    head = ["method", *map(str, df.columns)]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for idx, row in df.iterrows():
        lines.append("| " + " | ".join([str(idx), *map(str, row)]) + " |")
    return "\n".join(lines) + "\n"
