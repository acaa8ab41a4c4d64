"""The reports' figures (``report.html.png``): cut to the tight box as ``savefig(bbox_inches="tight")``
cuts them, drawn once; the same PNG bytes."""

from __future__ import annotations

import base64
import io

import matplotlib
import numpy as np
import pytest

from quadformer.report.html import png

matplotlib.use("Agg")


def _tight(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    return base64.b64encode(buf.getvalue()).decode()


def _figure(kind: str):
    import matplotlib.pyplot as plt

    rng = np.random.default_rng(3)
    t = np.arange(600) * 0.1
    if kind == "track":          # equal aspect, a legend placed where it fits best
        fig, ax = plt.subplots(figsize=(6.5, 6))
        ax.plot(np.cumsum(rng.normal(size=600)), np.cumsum(rng.normal(size=600)), ".", ms=2, label="fixes")
        ax.set_aspect("equal", adjustable="datalim")
        ax.legend(fontsize=7)
        ax.set_title("track", fontsize=9)
    elif kind == "stacked":      # shared x, a log and a symlog axis (mathtext ticks), a label below the figure
        fig, axes = plt.subplots(3, 1, figsize=(9, 2.5), sharex=True)
        axes[0].plot(t, rng.normal(size=600))
        axes[1].semilogy(t, np.exp(rng.normal(size=600)))
        axes[2].plot(t, 10 ** rng.uniform(-1, 3, 600))
        axes[2].set_yscale("symlog")
        axes[2].axvspan(10, 20, color="C3", alpha=0.15)
        axes[-1].set_xlabel("t (s)")
    else:                        # a layout engine moves the axes while saving
        fig, ax = plt.subplots(figsize=(4, 3), layout="constrained")
        ax.plot(t, np.sin(t))
        ax.set_ylabel("a long label on the left")
    return fig


@pytest.mark.parametrize("kind", ["track", "stacked", "constrained"])
def test_a_figure_is_the_png_savefig_cuts_to_its_tight_box(kind):
    import matplotlib.pyplot as plt

    once, tight = _figure(kind), _figure(kind)            # the same figure twice, each saved once
    try:
        assert png(once) == _tight(tight)
    finally:
        plt.close(once)
        plt.close(tight)
