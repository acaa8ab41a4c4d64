"""Stress evaluation: detectors tuned on a configuration, scored on attacks outside its tuning
ranges (``benchmark --stress``).

Each configuration of a profile gets small stress datasets (``Profile.stress_flights``
flights each, 24 on the quick profile; half attacked) of its own model and noise, each
simulated with its own seed derived from the configuration's and cached like every dataset.
No stress flight is used for fitting, hyper-parameters or thresholds: the detectors are the
tuned ones of the main run (same datasets, same split, same tuned-model cache), and every
stress flight is a test flight.

Which stress sets score which detector (``pairs``): a detector tuned on bias attacks is scored
on the bias-like sets (small offsets, long bias, freeze, replay, intermittent), one tuned on
ramp attacks on the drift-like sets (slow drifts, long ramps, sinusoid); one tuned on mixed
attacks on all of them (for it the four attack shapes are inside its training mix; small
offsets, slow drifts and long attacks are not). Every detector is also scored on its own
attack under Gaussian noise (the grid has exponential and Laplace noise only).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from quadformer.config import MIX, AttackConfig, SimConfig
from quadformer.dataset import Dataset
from quadformer.evaluation.metrics import evaluate, event_recall_by_type


@dataclass(frozen=True)
class StressSet:
    name: str
    what: str                              # what it changes, against the tuning distribution
    pairs: tuple[str, ...]                 # attack kinds of the configurations it scores
    attack: dict[str, Any] | None = None   # AttackConfig fields; None: the configuration's attack
    noise: str | None = None               # None: the configuration's noise shape
    duration: float | None = None          # s per flight; None: the profile's


_BIAS_LIKE = ("bias", MIX)
_DRIFT_LIKE = ("ramp", MIX)
LONG_FLIGHT_S = 90.0

STRESS_SETS: tuple[StressSet, ...] = (
    StressSet("small-offsets", "bias of norm 1-1.5 m (tuning: 1.5-6 m)", _BIAS_LIKE,
              {"kind": "bias", "magnitude": (1.0, 1.5)}),
    StressSet("long-bias", "bias lasting 30-60 s, onset 10-25 s, in 90 s flights (tuning: 5-20 s)", _BIAS_LIKE,
              {"kind": "bias", "onset": (10.0, 25.0), "duration": (30.0, 60.0)}, duration=LONG_FLIGHT_S),
    StressSet("freeze", "GPS fix frozen at its value at the onset, 5-20 s", _BIAS_LIKE, {"kind": "freeze"}),
    StressSet("replay", "GPS fix replaced by the honest fix of 3-10 s earlier, for 10-30 s", _BIAS_LIKE,
              {"kind": "replay"}),
    StressSet("intermittent", "bias of 1.5-6 m on for the first half of each 2-6 s period, 10-30 s", _BIAS_LIKE,
              {"kind": "intermittent"}),
    StressSet("slow-drifts", "ramp at 0.05-0.2 m/s (tuning: 0.2-1 m/s)", _DRIFT_LIKE,
              {"kind": "ramp", "rate": (0.05, 0.2)}),
    StressSet("long-ramp", "ramp lasting 30-60 s, onset 10-25 s, in 90 s flights (tuning: 10-30 s)", _DRIFT_LIKE,
              {"kind": "ramp", "onset": (10.0, 25.0), "duration": (30.0, 60.0)}, duration=LONG_FLIGHT_S),
    StressSet("sinusoid", "oscillating offset of 1.5-6 m at 0.05-0.5 Hz, 10-30 s", _DRIFT_LIKE,
              {"kind": "sinusoid"}),
    StressSet("gaussian-noise", "the configuration's own attack under Gaussian sensor noise (tuning: "
              "exponential or Laplace)", ("bias", "ramp", MIX), None, noise="gaussian"),
)


def stress_seed(seed: int, index: int) -> int:
    """Stress set ``index``'s dataset seed, derived from its configuration's seed."""
    return int(np.random.SeedSequence(seed, spawn_key=(0x57E55, index)).generate_state(1)[0])


def stress_configs(name: str, cfg: SimConfig, flights: int) -> list[tuple[str, StressSet, SimConfig]]:
    """(dataset name, stress set, config) of the stress datasets of configuration ``name``
    (``cfg``): its model, the sets paired with its attack kind, ``flights`` flights each."""
    out = []
    for i, st in enumerate(STRESS_SETS):
        if cfg.attack.kind not in st.pairs:
            continue
        attack = cfg.attack if st.attack is None else AttackConfig(fraction=cfg.attack.fraction, **st.attack)
        c = cfg.replace(attack=attack, noise=st.noise or cfg.noise, duration=st.duration or cfg.duration,
                        flights=flights, seed=stress_seed(cfg.seed, i))
        out.append((f"{name}-stress-{st.name}", st, c))
    return out


def stress_sets_doc() -> dict[str, dict[str, Any]]:
    """What each stress set is, for results.json."""
    return {st.name: {"what": st.what, "scores_detectors_tuned_on": list(st.pairs),
                      "flight_s": st.duration} for st in STRESS_SETS}


class StressPool:
    """Per (stress set, method), the per-step arrays of every configuration's stress flights,
    pooled into one evaluation (flight ids kept apart)."""

    def __init__(self) -> None:
        self._parts: dict[tuple[str, str], list[tuple[np.ndarray, ...]]] = {}
        self._next_id = 0

    def add(self, set_name: str, method: str, fid: np.ndarray, *arrays: np.ndarray, offset: int) -> None:
        self._parts.setdefault((set_name, method), []).append((fid + offset, *arrays))

    def reserve(self, n_ids: int) -> int:
        """A flight-id offset for ``n_ids`` more flights."""
        off = self._next_id
        self._next_id += int(n_ids)
        return off

    def results(self, rate: float) -> dict[str, dict[str, Any]]:
        out: dict[str, dict[str, Any]] = {}
        for (st, m), parts in self._parts.items():
            fid, t, y, s, a, b, off, types = (np.concatenate(x) for x in zip(*parts))
            res = evaluate(fid, t, y, s, a, gps_rate_hz=rate, offsets=off)
            res["event_recall_by_type"] = event_recall_by_type(fid, y, a, types)
            res["budget"] = _at_budget(fid, t, y, s, b, rate, off)
            res["configs"] = len(parts)
            out.setdefault(st, {})[m] = res
        return out


def _at_budget(fid, t, y, s, alarms, rate, offsets) -> dict[str, Any] | None:
    """The metrics at the false-alarm budget threshold (None for a detector without one)."""
    if not len(alarms) or np.isnan(alarms).any():
        return None
    return evaluate(fid, t, y, s, alarms.astype(bool), gps_rate_hz=rate, offsets=offsets, vus=False)


def score_stress(detectors: dict[str, Any], ds: Dataset, set_name: str, pool: StressPool | None = None
                 ) -> dict[str, dict[str, Any]]:
    """Every tuned detector (calibrated; ``threshold_`` from the main run's validation
    flights) on every flight of stress dataset ``ds``: per method, the metrics of
    ``evaluation.metrics.evaluate`` (false alarms per flight-hour on its clean flights), the
    event recall per attack type, and under ``budget`` the same metrics at the detector's
    false-alarm budget threshold (``budget_threshold_``, also chosen on the main run's
    validation flights: at most the budget of alarms per clean flight-hour there). Adds the
    per-step arrays to ``pool``."""
    f = ds.flights
    rate = ds.gps_rate_hz
    fid, t, y = f.flight_id.to_numpy(), f.t.to_numpy(), f.label.to_numpy()
    offsets = np.linalg.norm(f[["atk_d_x", "atk_d_y", "atk_d_z"]].to_numpy(), axis=1)
    types = np.where(y == 1, f.attack_type.astype(str).to_numpy(), "none")
    offset = pool.reserve(int(fid.max()) + 1) if pool is not None and len(fid) else 0
    out = {}
    for m, det in detectors.items():
        s = det.decision_function(f)
        alarms = s > det.threshold_
        res = evaluate(fid, t, y, s, alarms, gps_rate_hz=rate, offsets=offsets)
        res["event_recall_by_type"] = event_recall_by_type(fid, y, alarms, types)
        budget = getattr(det, "budget_threshold_", None)
        # NaN: no budget threshold (kept as an array so that every pooled part has the same fields)
        at_budget = (s > budget).astype(float) if budget is not None else np.full(len(s), np.nan)
        res["budget"] = _at_budget(fid, t, y, s, at_budget, rate, offsets)
        out[m] = res
        if pool is not None:
            pool.add(set_name, m, fid, t, y, s, alarms, at_budget, offsets, types, offset=offset)
    return out
