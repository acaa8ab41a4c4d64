"""The detection benchmark's outputs: tables in the paper's layout (Markdown, CSV, LaTeX),
figures (PNG) and report.html, from a results dict."""

from __future__ import annotations

import html
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from quadformer.dataset import load_dataset
from quadformer.evaluation.metrics import flight_events
from quadformer.io import atomic_write_text
from quadformer.report.html import img, page, png, table

NOISES = ("exponential", "laplace")
ATTACKS = ("bias", "ramp")
ATTACK_TITLE = {"bias": "Attack I (bias)", "ramp": "Attack II (ramp)"}


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
    for model in ("I", "II"):
        cols = pd.MultiIndex.from_tuples([(n, ATTACK_TITLE[a], m) for n in NOISES for a in ATTACKS
                                          for m in ("P", "R", "F1")])
        rows = []
        for method in methods:
            row = []
            for n in NOISES:
                for a in ATTACKS:
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
    out = [r"\begin{tabular}{l" + "c" * n + "}", r"\toprule",
           r"Model " + model + " & " + " & ".join(rf"\multicolumn{{6}}{{c}}{{{nz.capitalize()} noise}}"
                                                 for nz in NOISES) + r" \\",
           " & " + " & ".join(rf"\multicolumn{{3}}{{c}}{{{ATTACK_TITLE[a]}}}" for _ in NOISES
                              for a in ATTACKS) + r" \\",
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


def confusion_table(results: dict[str, Any], method: str) -> pd.DataFrame | None:
    total: dict[str, dict[str, int]] = {}
    found = False
    for c in results["configs"]:
        conf = c["methods"].get(method, {}).get("type_confusion")
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
                 "test flights, threshold-free AUROC/AUPRC, scores at the false-alarm budget threshold. "
                 "The point-adjusted F1 is shown only for comparison with the literature: it inflates "
                 "scores and is not the result.</p>")
    parts.append(table(extra, index=False))
    for key, b64 in figs.items():
        parts.append(f"<h3>{html.escape(key)}</h3>{img(b64)}")
    abl = ablation_table(results)
    if abl is not None:
        atomic_write_text(out / "ablation.csv", abl.to_csv())
        parts.append("<h2>QUADFormer ablations: point-wise F1 (test)</h2><p>noprior: no prior branch; nosup: no "
                     "supervised terms (no labels); nodisc: no discrepancy term.</p>")
        parts.append(table(abl))
    for m in results["methods_run"]:
        conf = confusion_table(results, m)
        if conf is not None:
            parts.append(f"<h2>{html.escape(m)}: attack type predicted at the first alarm of each alarm run</h2>"
                         "<p>Rows: true type (none: a false alarm); columns: predicted type; all test flights "
                         "of all configurations.</p>")
            parts.append(table(conf))
    parts.append("<h2>Versions</h2><pre>" + html.escape(str(results.get("versions", {}))) + "</pre>")
    doc = page("quadformer report", parts)
    atomic_write_text(out / "report.html", doc)
    return out / "report.html"
