"""The paper's eight configurations (Model I/II x exponential/laplace noise x bias/ramp), the
mixed-attack grid (Model I/II x exponential/laplace noise x mixed attacks) and the benchmark
profiles that size them."""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd
from scipy import stats

from quadformer.config import ATTACK_CHOICES, MIX, MODELS, NOISE_SHAPES, SimConfig
from quadformer.dataset import Dataset
from quadformer.evaluation.protocol import TrainingBudget

PAPER_GRID = tuple(itertools.product(("I", "II"), ("exponential", "laplace"), ("bias", "ramp")))
#: mixed attacks: every attacked flight draws its kind from all six (``AttackConfig.mix``)
MIXED_GRID = tuple(itertools.product(("I", "II"), ("exponential", "laplace"), (MIX,)))


@dataclass(frozen=True)
class Profile:
    name: str
    flights: int            # per configuration
    duration: float = 60.0  # s per flight
    seed: int = 0           # datasets' seed (each configuration derives its own from it)
    grid: tuple[tuple[str, str, str], ...] = PAPER_GRID   # (model, noise, attack) configurations
    stress_flights: int = 24   # flights per stress dataset (``benchmark --stress``)
    #: a reduced training budget for every trained method (None: the full, paper's budget)
    budget: TrainingBudget | None = None
    #: the configurations the resilience run flies (None: the whole grid)
    resilience_grid: tuple[tuple[str, str, str], ...] | None = None

    def for_resilience(self) -> "Profile":
        """This profile over the configurations its resilience run flies."""
        return self if self.resilience_grid is None else dataclasses.replace(self, grid=self.resilience_grid)


#: the demo's training budget, chosen by measurement so that ``make demo`` stays short: an
#: eighth of every trained method's epochs and windows (see the README's demo section)
DEMO_BUDGET = TrainingBudget("demo", 0.125)
#: the demo's resilience run: four of the eight configurations, each model, noise shape and
#: attack twice (every pair of them once)
DEMO_RESILIENCE_GRID = (("I", "exponential", "bias"), ("I", "laplace", "ramp"), ("II", "exponential", "ramp"),
                        ("II", "laplace", "bias"))


PROFILES = {
    "demo": Profile("demo", 20, stress_flights=12, budget=DEMO_BUDGET, resilience_grid=DEMO_RESILIENCE_GRID),
    "quick": Profile("quick", 60),
    "paper": Profile("paper", 600, stress_flights=120),
    "mixed": Profile("mixed", 60, grid=MIXED_GRID),
}


def get_profile(profile: str | Profile) -> Profile:
    if isinstance(profile, Profile):
        return profile
    try:
        return PROFILES[profile]
    except KeyError:
        raise ValueError(f"profile: unknown profile {profile!r}; choose from {', '.join(PROFILES)}") from None


def config_name(model: str, noise: str, attack: str) -> str:
    return f"model{model}-{noise}-{attack}"


def select_configs(profile: Profile, names: str) -> Profile:
    """``profile`` over some of its configurations: ``names`` comma-separated configuration
    names (``modelI-exponential-bias``, ...), kept in the profile's order. The datasets are
    those of the whole profile (each configuration's seed derives from its own names), so
    a selection reuses, and adds to, the whole profile's cache."""
    wanted = [n.strip() for n in names.split(",") if n.strip()]
    if not wanted:
        raise ValueError("configs: no configuration named")
    named = {config_name(*c): c for c in profile.grid}
    unknown = [n for n in wanted if n not in named]
    if unknown:
        raise ValueError(f"configs: {', '.join(map(repr, unknown))} not in profile {profile.name!r}; "
                         f"choose from {', '.join(named)}")
    grid = tuple(c for n, c in named.items() if n in wanted)
    res = None if profile.resilience_grid is None else tuple(c for c in profile.resilience_grid if c in grid)
    return dataclasses.replace(profile, grid=grid, resilience_grid=res or None)


def noise_stats(ds: Dataset) -> dict[str, float]:
    """Moments of the GPS velocity noise (white, of the configured shape) on clean steps."""
    f = ds.flights[ds.flights["label"] == 0]
    err = (f[["gps_vel_x", "gps_vel_y", "gps_vel_z"]].to_numpy()
           - f[["true_vel_x", "true_vel_y", "true_vel_z"]].to_numpy()).reshape(-1)
    return {"std": float(err.std()), "skewness": float(stats.skew(err)),
            "excess_kurtosis": float(stats.kurtosis(err))}


def dataset_summary(ds: Dataset) -> dict[str, Any]:
    s = dict(ds.meta["summary"])
    s["attacked_fraction"] = s["attacked_flights"] / s["flights"]
    s["gps_vel_noise"] = noise_stats(ds)
    return s


def config_seed(seed: int, model: str, noise: str, attack: str) -> int:
    """Each configuration's own dataset seed, derived from ``seed``: configurations do not
    share missions or noise realisations (which would make them near copies). The paper's
    eight keep the seeds they always had; any other (model, noise, attack) derives its own
    from its names' indices under a different key."""
    if (model, noise, attack) in PAPER_GRID:
        key: tuple[int, ...] = (0xC0F, PAPER_GRID.index((model, noise, attack)))
    else:
        key = (0xC0F, 0x1, MODELS.index(model), NOISE_SHAPES.index(noise), ATTACK_CHOICES.index(attack))
    return int(np.random.SeedSequence(seed, spawn_key=key).generate_state(1)[0])


def profile_configs(profile: Profile) -> list[tuple[str, SimConfig]]:
    """(name, config) of the profile's configurations (``profile.grid``) at its size."""
    base = SimConfig(flights=profile.flights, duration=profile.duration, seed=profile.seed)
    return [(config_name(*c), grid_config(base, *c)) for c in profile.grid]


def grid_config(base: SimConfig, model: str, noise: str, attack: str) -> SimConfig:
    """``base`` with one paper configuration and its derived seed; attack ranges take that
    attack's defaults."""
    atk = {**base.attack.__dict__, "kind": attack, "duration": None, "magnitude": None, "rate": None,
           "frequency": None, "period": None, "delay": None}
    return base.replace(model=model, noise=noise, attack=base.attack.__class__(**atk),
                        seed=config_seed(base.seed, model, noise, attack))


def summary_table(rows: list[dict[str, Any]]) -> pd.DataFrame:
    return pd.DataFrame([{
        "config": r["config"],
        "flights": r["flights"],
        "attacked": f"{r['attacked_fraction']:.2f}",
        "gps noise std": f"{r['gps_vel_noise']['std']:.3f}",
        "skew": f"{r['gps_vel_noise']['skewness']:.2f}",
        "ex.kurt": f"{r['gps_vel_noise']['excess_kurtosis']:.2f}",
        "NIS clean": _fmt(r["mean_nis_clean"]),
        "NIS attacked": _fmt(r["mean_nis_attacked"]),
        "max dev clean (m)": _fmt(r["max_deviation_clean_m"]),
        "max dev attacked (m)": _fmt(r["max_deviation_attacked_m"]),
    } for r in rows])


def _fmt(x: float | None) -> str:
    return "-" if x is None or not np.isfinite(x) else f"{x:.2f}"
