"""The outputs of a detection benchmark over several seeds: each metric's spread over the seeds
per method and configuration (CSV, Markdown) and report.html."""

from __future__ import annotations

import html
from pathlib import Path
from typing import Any

import pandas as pd

from quadformer.io import atomic_write_text
from quadformer.report.html import page, table, versions


def seeds_table(results: dict[str, Any], metric: str = "f1") -> pd.DataFrame:
    """One metric over the seeds: rows methods, columns configurations, cells
    "mean ± std [min, max]" (``experiments.seeds.run_seeds``' summary)."""
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
    parts.append(versions(results.get("versions")))
    atomic_write_text(out / "report.html", page("quadformer report over seeds", parts))
    return out / "report.html"


def _markdown_plain(df: pd.DataFrame) -> str:
    head = ["method", *map(str, df.columns)]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for idx, row in df.iterrows():
        lines.append("| " + " | ".join([str(idx), *map(str, row)]) + " |")
    return "\n".join(lines) + "\n"
