"""The report of detection on one flight log: what the log holds, the track, the
innovations, the score against the threshold with the alarms, and the receiver's indicators."""

from __future__ import annotations

import html
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from quadformer.detectors import alert_counts, alerts_frame
from quadformer.io import atomic_write_text, package_versions
from quadformer.report.html import img, page, png, table, versions


#: alerts listed open in a log's report up to this many (more: the section starts folded)
MANY_ALERTS = 20


#: a log report's figures by layout, kept in this process and drawn again for the next log
_KEPT: dict[tuple, tuple] = {}


def _canvas(n: int, figsize: tuple[float, float]):
    """(figure, axes) of ``n`` panels stacked on one time axis (one panel: the track), cleared of
    the previous log's lines, spans, legends and titles. A fleet's reports draw three figures per
    log: the figure, its axes and their tick marks are made once per layout and process (making
    them anew was half of each figure's time); each log's data sets the limits again."""
    key = (n, figsize)
    if key not in _KEPT:
        from matplotlib.figure import Figure

        fig = Figure(figsize=figsize)
        _KEPT[key] = fig, fig.subplots(n, 1, sharex=n > 1, squeeze=False)[:, 0]
    fig, axes = _KEPT[key]
    for ax in axes:
        for artist in [*ax.lines, *ax.patches, *ax.collections, *ax.texts]:
            artist.remove()
        if ax.get_legend() is not None:
            ax.get_legend().remove()
        ax.set_title("")
        ax.set_xlabel("")
        ax.set_ylabel("")
        ax.set_yscale("linear")
        ax.set_prop_cycle(None)         # the colours start again at C0
        ax.relim()
        ax.set_autoscale_on(True)
    return fig, axes


def _figures(det) -> dict[str, str]:
    rows, alarms = det.rows, np.asarray(det.alarms, bool)
    thr = det.detector.threshold_ if hasattr(det, "detector") else None
    figs: dict[str, str] = {}

    # top-down track: the fixes, the replayed estimate, the autopilot's own estimate
    fig, (ax,) = _canvas(1, (6.5, 6))
    ax.plot(rows.gps_pos_x, rows.gps_pos_y, ".", ms=2, color="0.55", label="GPS fixes")
    if "est_pos_x" in rows:
        ax.plot(rows.est_pos_x, rows.est_pos_y, "-", lw=1, color="C0", label="estimate (replayed filter)")
    if "ap_pos_x" in rows:
        ax.plot(rows.ap_pos_x, rows.ap_pos_y, "--", lw=1, color="C2", label="autopilot's estimate")
    if "true_pos_x" in rows:
        ax.plot(rows.true_pos_x, rows.true_pos_y, ":", lw=1, color="k", label="simulator truth")
    if alarms.any():
        ax.plot(rows.gps_pos_x[alarms], rows.gps_pos_y[alarms], "x", ms=5, color="C3", label="fix under alarm")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(fontsize=7)
    ax.set_title("track (local ENU about the log's origin)", fontsize=9)
    figs["track"] = _save(fig)

    # innovations, NIS, score
    t = rows.t.to_numpy()
    has_nis = "res_gps_nis" in rows
    fig, axes = _canvas(3 if has_nis else 2, (9, 6.5 if has_nis else 4.5))
    for a, c in zip("xyz", ("C0", "C1", "C2")):
        axes[0].plot(t, rows[f"res_gps_r_p{a}"], lw=0.8, color=c, label=f"position innovation {a}")
    axes[0].set_ylabel("m")
    axes[0].legend(fontsize=7, loc="upper left")
    k = 1
    if has_nis:
        axes[1].semilogy(t, np.maximum(rows.res_gps_nis, 1e-3), lw=0.8, color="k")
        _plain_ticks(axes[1])
        axes[1].set_ylabel("GPS NIS")
        k = 2
    axes[k].plot(t, det.scores, lw=0.8, color="k", label="score")
    if thr is not None:
        axes[k].axhline(thr, color="C3", ls="--", lw=0.8, label="threshold")
    for s, e in _spans(t, alarms):
        for ax in axes:
            ax.axvspan(s, e, color="C3", alpha=0.15)
    if "label" in rows and rows.label.any():
        for s, e in _spans(t, rows.label.to_numpy() == 1):
            axes[k].axvspan(s, e, color="orange", alpha=0.2)
    axes[k].set_ylabel("score")
    axes[k].set_yscale("symlog")
    _plain_ticks(axes[k])
    axes[k].legend(fontsize=7, loc="upper left")
    axes[-1].set_xlabel("t (s from the log start); red: alarms")
    figs["innovations_and_score"] = _save(fig)

    # the receiver's own indicators
    cols = [c for c in ("gps_satellites", "gps_eph", "gps_epv", "gps_fix_type", "gps_jamming", "gps_spoofing")
            if c in rows and np.isfinite(rows[c].to_numpy(float)).any()]
    if cols:
        fig, axes = _canvas(len(cols), (9, 1.3 * len(cols) + 0.5))
        for ax, c in zip(axes, cols):
            ax.step(t, rows[c], where="post", lw=0.9)
            ax.set_ylabel(c.replace("gps_", ""), fontsize=8)
        axes[-1].set_xlabel("t (s)")
        figs["receiver"] = _save(fig)
    return figs


def _save(fig) -> str:
    """The figure as PNG within set margins (inches: room for the tick labels and the axis labels).
    A report per log of a fleet draws three figures per log: measuring each one's tight box cost
    as much as drawing it."""
    w, h = fig.get_size_inches()
    fig.subplots_adjust(left=0.85 / w, right=1 - 0.2 / w, bottom=0.6 / h, top=1 - 0.35 / h)
    return png(fig, tight=False)


def _plain_ticks(ax) -> None:
    """A log axis labelled in plain numbers (1, 10, 100), its minor ticks unlabelled: the
    default powers of ten are typeset one label at a time, the slowest part of a log report."""
    from matplotlib.ticker import FuncFormatter, NullFormatter

    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.yaxis.set_minor_formatter(NullFormatter())


def _spans(t: np.ndarray, mask: np.ndarray) -> list[tuple[float, float]]:
    from quadformer.detectors import runs
    return [(float(t[s]), float(t[e - 1])) for s, e in runs(mask)]


def _log_info(log) -> dict[str, Any]:
    return {"log": str(log.path), "format": log.source,
            "vehicle": ", ".join(f"{k} {v}" for k, v in log.vehicle.items()),
            "duration (s)": f"{log.duration:.1f}", "segments": len(log.segments),
            "streams": ", ".join(log.streams), "events": _event_counts(log.events),
            "origin": f"{log.origin} ({log.origin_source})"}


def _event_counts(events) -> str:
    if events is None:
        return "none logged"
    return ", ".join(f"{k} {n}" for k, n in events["event"].value_counts(sort=False).items())


def _info_table(info: dict[str, Any]) -> str:
    return table(pd.DataFrame({"": list(info), "value": [str(v) for v in info.values()]}), index=False)


def _notes(notes: list[str]) -> str:
    return ("<h2>What the reader and the replay did</h2><ul>"
            + "".join(f"<li>{html.escape(n)}</li>" for n in notes) + "</ul>")


def write_unscored_report(log, reason: str, out: Path) -> Path:
    """report.html of a readable log with nothing to score, saying why."""
    parts = [f"<h1>quadformer detect: {html.escape(log.path.name)}</h1>", _info_table(_log_info(log)),
             f"<h2>Nothing scored</h2><p>{html.escape(reason)}</p>", _notes(log.notes), versions(package_versions())]
    atomic_write_text(Path(out) / "report.html", page(f"quadformer detect {log.path.name}", parts, width_px=1000))
    return Path(out) / "report.html"


def _alert_lines(alerts) -> dict[str, Any]:
    """The alerts counted apart: spoofing alerts in the air first, the others beside."""
    n = alert_counts(alerts)
    return {"spoofing alerts in the air": n["alerts"],
            "beside them": f"{n['alerts_ground']} on the ground, {n['alerts_transition']} in the take-off "
                           f"transition, {n['alerts_degraded']} of a degraded receiver ({n['alerts_total']} in all)"}


def write_log_report(det, out: Path, model: str) -> Path:
    """report.html of one log's detection (``logs.detect.LogDetection``) into ``out``."""
    out = Path(out)
    log = det.log
    info: dict[str, Any] = {
        **_log_info(log), "residues": det.residues, "sensors fused": det.sensors,
        "detector": f"{det.detector.name} ({model})",
        "threshold": f"{det.detector.threshold_:.4g}", "GPS steps scored": len(det.rows),
        "steps under alarm": int(np.sum(det.alarms)), **_alert_lines(det.alerts),
    }
    parts = [f"<h1>quadformer detect: {html.escape(log.path.name)}</h1>", _info_table(info)]
    # figures first (the scores and alarms over the flight, the track, the receiver), then the alerts
    figs = _figures(det)
    for key in sorted(figs, key=lambda k: k != "innovations_and_score"):
        parts.append(f"<h2>{html.escape(key.replace('_', ' '))}</h2>{img(figs[key])}")
    n = len(det.alerts)
    parts.append(f"<details{' open' if n <= MANY_ALERTS else ''}><summary><h2 style='display:inline'>Alerts "
                 f"({n})</h2></summary>"
                 + (table(alerts_frame(det.alerts), ".3g", index=False) if n else "<p>none</p>") + "</details>")
    parts.append(_notes([*log.notes, *det.notes]))
    parts.append(versions(package_versions()))
    atomic_write_text(out / "report.html", page(f"quadformer detect {log.path.name}", parts, width_px=1000))
    return out / "report.html"
