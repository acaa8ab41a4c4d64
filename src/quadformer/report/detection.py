"""The detection benchmark's outputs: tables in the paper's layout (Markdown, CSV, LaTeX),
figures (PNG) and report.html, from a results dict."""

from __future__ import annotations

import html
from pathlib import Path
from typing import Any

import pandas as pd

from quadformer.detectors.attack_types import ShapeTyper
from quadformer.io import atomic_write_text
from quadformer.report.detection_figures import figures
from quadformer.report.detection_tables import (TYPE_CONFUSIONS, ablation_table, confusion_table, dataset_table,
                                                extra_table, paper_tables, stress_table, to_latex, to_markdown,
                                                type_recall_table, typing_table)
from quadformer.report.html import img, page, table, versions


def _fold(title: str, body: str, open_: bool = False) -> str:
    """A section that opens and closes (``<details>``), its title always shown."""
    return (f"<details{' open' if open_ else ''}><summary><h2 style='display:inline'>{html.escape(title)}</h2>"
            f"</summary>{body}</details>")


def write_report(results: dict[str, Any], out: Path) -> Path:
    """Write table_model_{I,II}.{md,csv,tex}, metrics.csv, figures/ and report.html into out."""
    out = Path(out)
    tables = paper_tables(results)
    for key, df in tables.items():
        model = key.split("_")[1]
        atomic_write_text(out / f"table_{key}.md", to_markdown(df))
        flat = df.copy()
        flat.columns = [f"{n}/{a}/{m}" for n, a, m in df.columns]
        atomic_write_text(out / f"table_{key}.csv", flat.to_csv(index_label="method"))
        atomic_write_text(out / f"table_{key}.tex", to_latex(df, model))
    extra = extra_table(results)
    atomic_write_text(out / "metrics.csv", extra.to_csv(index=False))
    figs = figures(results, out)

    if results.get("profile") is not None:
        head = (f"<h1>quadformer benchmark: profile {html.escape(results['profile'])}</h1>"
                f"<p>{results['flights_per_config']} flights of {results['duration_s']:.0f} s per configuration; ")
    else:
        head = (f"<h1>quadformer benchmark: {len(results['configs'])} dataset(s)</h1><p>datasets: "
                + ", ".join(html.escape(c["dataset"]) for c in results["configs"]) + "; ")
    parts = [head + f"protocol: {html.escape(results['protocol'])}. "
             + ("Every detector is a shipped one: " + ", ".join(html.escape(v) for v in results["shipped"].values())
                + " (<code>quadformer zoo show NAME</code>).</p>" if results.get("shipped") else
                f"Labels of {results['label_fraction']:.0%} of the training flights are available to every "
                "method.</p>")]
    # figures first: F1 with its interval, delay against false alarms, one example flight
    examples = [k for k in figs if k.startswith("example_")]
    parts.append("<h2>At a glance</h2><p>Point-wise F1 on the test flights with its 95% bootstrap interval over "
                 "flights, by method and configuration:</p>" + img(figs["f1_by_config"]))
    parts.append("<p>Median detection delay against false alarms per clean test flight-hour (each point a "
                 "method on one configuration):</p>" + img(figs["delay_vs_false_alarms"]))
    if examples:
        parts.append(f"<p>An attacked test flight ({html.escape(examples[0].removeprefix('example_'))}): its "
                     "GPS innovation, each method's score, threshold and alarms:</p>" + img(figs[examples[0]]))
    for key, df in tables.items():
        parts.append(_fold(f"Model {key.split('_')[1]}: point-wise precision, recall, F1 (test flights)",
                           table(df), open_=True))
    if not tables:
        df = dataset_table(results)
        flat = df.copy()
        flat.columns = [f"{d}/{m}" for d, m in df.columns]
        atomic_write_text(out / "table_datasets.csv", flat.to_csv(index_label="method"))
        parts.append(_fold("Point-wise precision, recall, F1 (test flights)", table(df), open_=True))
    parts.append(_fold("All metrics (every method and configuration)",
                       "<p>Event-wise scores, detection delays, false alarms per hour on clean "
                       "test flights, threshold-free AUROC/AUPRC and VUS-PR (range-based PR area averaged over label "
                       "buffers of 0 to 5 s, Paparrizos et al.), a 95% bootstrap interval of the F1 over test "
                       "flights, scores at the false-alarm budget threshold. "
                       "The point-adjusted F1 is shown only for comparison with the literature: it inflates "
                       "scores and is not the result.</p>" + table(extra, index=False)))
    rest = [k for k in figs if k not in ("f1_by_config", "delay_vs_false_alarms") and k != (examples or [None])[0]]
    if rest:
        parts.append(_fold("More figures: the delays' spread, the other example flights",
                           "".join(f"<h3>{html.escape(k)}</h3>{img(figs[k])}" for k in rest)))
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
    parts.append(versions(results.get("versions")))
    doc = page("quadformer report", parts)
    atomic_write_text(out / "report.html", doc)
    return out / "report.html"
