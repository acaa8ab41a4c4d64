"""Building blocks of the offline HTML reports: embedded PNG figures, tables, the page."""

from __future__ import annotations

import base64
import html
import io
from collections.abc import Mapping

import pandas as pd


def png(fig, dpi: float = 110, tight: bool = True) -> str:
    """A matplotlib figure as base64 PNG, for an ``<img src='data:image/png;base64,...'>``: the
    figure cut to its tight bounding box, as ``savefig(bbox_inches="tight")`` cuts it (``tight``
    False: the figure as laid out, drawn once, for a figure whose margins are set). That box is
    measured here on the canvas's renderer at the saving resolution, and given to ``savefig``,
    which then draws the figure once instead of twice (its first drawing, for the box alone, costs
    as much as the second: a report per log drew each figure twice); the same PNG, byte for byte."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches=_tight_box(fig, dpi) if tight else None)
    return base64.b64encode(buf.getvalue()).decode()


def _tight_box(fig, dpi: float):
    """``savefig``'s tight box of ``fig`` at ``dpi``, padded as it pads it; "tight" (savefig measures
    it) where a layout engine moves the axes while saving or the canvas has no Agg renderer."""
    import matplotlib

    get_renderer = getattr(fig.canvas, "get_renderer", None)
    if fig.get_layout_engine() is not None or get_renderer is None:
        return "tight"
    kept = fig.dpi
    fig.dpi = dpi
    try:
        return fig.get_tightbbox(get_renderer()).padded(matplotlib.rcParams["savefig.pad_inches"])
    finally:
        fig.dpi = kept


def img(b64: str) -> str:
    return f"<img src='data:image/png;base64,{b64}'/>"


def table(df: pd.DataFrame, digits: str = ".2f", index: bool = True) -> str:
    return df.to_html(index=index, float_format=lambda v: f"{v:{digits}}", na_rep="-", border=0, classes="t")


def versions(versions: Mapping[str, str] | None) -> str:
    """A report's "Versions" section: the packages a run used (``io.package_versions``) as a
    two-column table, package and version, in the order recorded."""
    if not versions:
        return "<h2>Versions</h2><p>not recorded</p>"
    rows = "".join(f"<tr><td>{html.escape(str(k))}</td><td>{html.escape(str(v))}</td></tr>"
                   for k, v in versions.items())
    return ("<h2>Versions</h2><table class='t versions'><thead><tr><th>package</th><th>version</th></tr></thead>"
            f"<tbody>{rows}</tbody></table>")


def page(title: str, parts: list[str], width_px: int = 1200) -> str:
    """A self-contained page (no external resources: it reads offline)."""
    style = (f"<style>body{{font-family:sans-serif;max-width:{width_px}px;margin:auto}}"
             "table.t{border-collapse:collapse;font-size:12px}table.t td,table.t th{padding:2px 6px;"
             "border-bottom:1px solid #ddd;text-align:right}img{max-width:100%}</style>")
    return (f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>{style}"
            f"</head><body>{''.join(parts)}</body></html>")
