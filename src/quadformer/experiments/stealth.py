"""The stealth benchmark: how far an attacker who knows the detector moves the vehicle before
anything alarms.

For each shipped detector of the plan, on flights of the simulation that detector was calibrated
on (its model card's ``sim_config``: the vehicle, the sensors and their noise), every flight is
attacked from ``onset`` to its end by a stealthy attacker (``attacks.stealthy``):

- ``white`` box at each ``margin``: the attacker runs the detector's own stream on each fix it
  sends and keeps the score under margin x threshold, moving the fix at most ``rate`` m/s;
- ``grey`` box at each ``margin``: the white box's search on a surrogate the attacker made
  itself (``fit_surrogate``): the same method with the shipped detector's parameters, fitted on
  ``SURROGATE_FLIGHTS`` clean flights of its own (the other airframe, other seeds) and alarmed at
  their false-alarm-budget threshold. It knows the method, not the vehicle's calibration; the
  learned detectors are not attacked so (the attacker would train a network of its own);
- with ``rehearse`` (accelerations, m/s^2), the white and grey boxes plan: before the attack each
  rehearses the fastest push (no plan) and a plan at each of those accelerations (``rehearse``) on
  ``REHEARSAL_FLIGHTS`` flights of its own, and flies the one that went farthest unseen;
- ``black`` box: no score; the fix drifts in at ``accel`` m/s^2 up to ``rate`` (flown once per
  simulation, scored by each detector of it): the slow shape an attacker without the detector
  would choose, and the fixed shape the white box is compared with.

The defender is the detector itself, scored offline on the flights (a stream's scores equal its
offline ones) at its shipped false-alarm-budget threshold; what the attack reached, and the
physical bound beside it, are measured by ``experiments.stealth_envelope``.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pandas as pd

from quadformer.config import KNOWLEDGE, MAX_HEADINGS, MODELS, SimConfig
from quadformer.experiments.stealth_envelope import BOUND_Z, CEILING_SHARE, envelope, physical_bound, summarise
from quadformer.report.stealth import plan_name, write_stealth_report

HORIZONS = (10.0, 30.0, 60.0, 120.0)
#: the GPS policies a stealth run flies under (``StealthPlan.policies``)
POLICIES = ("none", "resilient")
#: the grey-box attacker's own clean flights: half fit its surrogate, half set its threshold
SURROGATE_FLIGHTS = 6
#: added to the plan's seed for the attacker's own flights (none of them is a flight it attacks)
SURROGATE_SEED = 7919
#: the flights an attacker rehearses each of its plans on, and the seed added for them
REHEARSAL_FLIGHTS = 2
REHEARSAL_SEED = 104729
#: the plans the full profile's white and grey boxes rehearse (m/s^2): the black box's 0.05 among them
REHEARSE = (0.02, 0.05, 0.2)


@dataclass(frozen=True)
class StealthPlan:
    detectors: tuple[str, ...]
    knowledge: tuple[str, ...] = ("white", "black")
    margins: tuple[float, ...] = (0.8,)
    flights: int = 4
    horizons: tuple[float, ...] = HORIZONS
    onset: float = 10.0
    rate: float = 3.0          # m/s, the attacker's top speed
    accel: float = 0.05        # m/s^2, the black box's acceleration
    seed: int = 0
    #: the GPS policies flown: "none" (GPS always fused: the deviation unseen), "resilient" (the
    #: detector's alarms drive the resilient policy in the loop: the deviation the attack reaches)
    policies: tuple[str, ...] = ("none",)
    #: the axes the white and grey boxes search at each GPS step (``AttackConfig.headings``): 1 along
    #: the attack's direction only; more, across the track too
    headings: int = 1
    #: the plans' accelerations (m/s^2) the white and grey boxes rehearse beside the fastest push
    #: (``rehearse``); empty: they fly the fastest push, unrehearsed
    rehearse: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if not self.detectors:
            raise ValueError("stealth: name at least one detector")
        bad = [k for k in self.knowledge if k not in KNOWLEDGE]
        if not self.policies or set(self.policies) - set(POLICIES):
            raise ValueError(f"stealth: policies must name some of {', '.join(POLICIES)}, got {self.policies!r}")
        if not self.knowledge:
            raise ValueError(f"stealth: name at least one attacker's knowledge of {', '.join(KNOWLEDGE)}")
        if bad:
            raise ValueError(f"stealth: knowledge {bad[0]!r}; choose from {', '.join(KNOWLEDGE)}")
        if any(not 0.0 < m <= 1.0 for m in self.margins):
            raise ValueError(f"stealth: margins must be in (0, 1], got {self.margins}")
        if not (isinstance(self.headings, int) and 1 <= self.headings <= MAX_HEADINGS):
            raise ValueError(f"stealth: headings must be a whole number from 1 to {MAX_HEADINGS}, "
                             f"got {self.headings!r}")
        if any(not (np.isfinite(a) and a > 0) for a in self.rehearse):
            raise ValueError(f"stealth: rehearse takes positive accelerations (m/s^2), got {self.rehearse!r}")
        if self.rehearse and self.headings > 1:
            raise ValueError("stealth: a rehearsed plan runs along the attack's direction: headings must be 1 "
                             "(or rehearse nothing)")
        if self.flights < 1 or not self.horizons or min(self.horizons) <= 0:
            raise ValueError("stealth: at least one flight and positive horizons")

    @property
    def duration(self) -> float:
        return self.onset + max(self.horizons)


#: the profiles of ``quadformer benchmark --profile``: every shipped detector of every set (the
#: autopilot sets' tests on the innovations the simulated filter logs as that autopilot), and a
#: small one
PROFILES = {
    "stealth": StealthPlan(detectors=("vio-quadformer", "vio-cusum", "vio-chi2", "vio-cusum-ref", "vio-sprt",
                                      "vio-bht", "vio-chi2-vref", "vio-cusum-vref",
                                      "magbaro-glr", "magbaro-quadformer", "magbaro-cusum", "magbaro-chi2",
                                      "magbaro-cusum-ref", "magbaro-cusum-vref", "px4-cusum", "px4-chi2",
                                      "ardupilot-glr", "ardupilot-cusum", "ardupilot-chi2"),
                           knowledge=("white", "grey", "black"),
                           margins=(0.5, 0.8), flights=3, policies=("none", "resilient"), rehearse=REHEARSE),
    "stealth-quick": StealthPlan(detectors=("vio-cusum", "magbaro-cusum"), flights=2, horizons=(10.0, 30.0)),
}


def stealth_config(detector: str, plan: StealthPlan, knowledge: str, margin: float | None,
                   det=None, surrogate: Path | None = None, plan_accel: float | None = None) -> SimConfig:
    """The flights a detector is attacked on: its calibration's simulation, every flight attacked.
    ``det``: the shipped detector ``detector`` already loaded (else it is loaded here);
    ``surrogate``: the grey box's model file (``fit_surrogate``); ``plan_accel``: the white or grey
    box's plan (``rehearse``; None: the fastest push)."""
    if det is None:
        from quadformer.detectors import pretrained

        det = pretrained.load(detector)
    sim = calibration_sim(det, detector)
    sim.update(flights=plan.flights, duration=plan.duration, batch_size=plan.flights, seed=plan.seed)
    attack = _attack(plan, detector, knowledge, margin, plan_accel)
    if knowledge == "grey":
        if surrogate is None:
            raise ValueError(f"stealth: a grey-box attack on {detector} needs its surrogate (fit_surrogate)")
        attack["surrogate"] = str(surrogate)
    sim["attack"] = attack
    return SimConfig.from_dict(sim)


def _attack(plan: StealthPlan, detector: str, knowledge: str, margin: float | None,
            plan_accel: float | None) -> dict[str, Any]:
    """The plan's stealthy attack on every flight, by an attacker of ``knowledge`` against ``detector``."""
    attack = {"kind": "stealthy", "detector": detector, "knowledge": knowledge, "fraction": 1.0,
              "onset": (plan.onset, plan.onset), "rate": (plan.rate, plan.rate), "accel": (plan.accel, plan.accel)}
    if knowledge in ("white", "grey"):
        attack["margin"] = margin
        if plan.headings > 1:
            attack["headings"] = plan.headings
        if plan_accel is not None:
            attack["plan_accel"] = plan_accel
    return attack


def calibration_sim(det, name: str) -> dict[str, Any]:
    """A copy of the simulation configuration ``det`` (named ``name``) was calibrated on."""
    sim = dict((getattr(det, "calibration_", None) or {}).get("sim_config") or {})
    if not sim:
        raise ValueError(f"stealth: {name} records no simulation it was calibrated on")
    return sim


def learned(det) -> bool:
    """Whether ``det`` is a network (its surrogate would be a network the attacker trains)."""
    return type(det).__module__.startswith("quadformer.detectors.neural")


def surrogate_config(det, plan: StealthPlan) -> SimConfig:
    """The grey-box attacker's own flights: the simulation ``det`` was calibrated on, flown with
    the other airframe and other seeds, clean."""
    sim = calibration_sim(det, det.name)
    model = sim.get("model", MODELS[0])
    sim.update(model=next(m for m in MODELS if m != model), flights=SURROGATE_FLIGHTS, duration=plan.duration,
               batch_size=SURROGATE_FLIGHTS, seed=plan.seed + SURROGATE_SEED, attack={"kind": "none"})
    return SimConfig.from_dict(sim)


def fit_surrogate(det, plan: StealthPlan, path: Path) -> dict[str, Any]:
    """The grey box's surrogate of ``det``, written to ``path``: a detector of the same method and
    parameters fitted on half the attacker's own clean flights (``surrogate_config``) and alarmed
    at the false-alarm-budget threshold of the other half (at most one alarm run per flight-hour:
    on a few minutes of flight, their largest score). Returns what it is, for the results."""
    from quadformer.simulation import simulate

    if learned(det):
        raise ValueError(f"stealth: {det.name} is a network; a grey-box attacker would train its own "
                         "(not run: knowledge grey covers the methods fitted without training)")
    cfg = surrogate_config(det, plan)
    flights = simulate(cfg).flights
    ids = np.sort(flights.flight_id.unique())
    half = len(ids) // 2
    sur = type(det)(**det.get_params())
    sur.fit(flights[flights.flight_id.isin(ids[:half])].reset_index(drop=True))
    sur.calibrate(flights[flights.flight_id.isin(ids[half:])].reset_index(drop=True), criterion="budget")
    path.parent.mkdir(parents=True, exist_ok=True)
    sur.save(path)
    return {"file": path.name, "threshold": float(sur.threshold_), "model": cfg.model, "seed": cfg.seed,
            "flights_fit": int(half), "flights_threshold": int(len(ids) - half)}


def rehearse(det, name: str, plan: StealthPlan, knowledge: str, margin: float,
             surrogate: Path | None = None) -> dict[str, Any]:
    """The plan a white or grey box flies against ``det`` (the shipped detector ``name``): the
    fastest push and a plan at each of ``plan.rehearse``'s accelerations, each flown on
    ``REHEARSAL_FLIGHTS`` flights of the attacker's own, and judged by the median over them of the
    deviation unseen by the last horizon. The white box rehearses on the vehicle's simulation
    (other seeds) against the detector itself; the grey box on its surrogate's (the other airframe,
    ``surrogate_config``) against its surrogate at the surrogate's threshold: it never sees the
    vehicle's. Returns ``{"accel": the chosen (None: the fastest push), "tried": [...]}``."""
    from quadformer.simulation import simulate

    T = max(plan.horizons)
    seed = plan.seed + REHEARSAL_SEED
    if knowledge == "grey":
        if surrogate is None:
            raise ValueError(f"stealth: a grey-box rehearsal against {name} needs its surrogate (fit_surrogate)")
        from quadformer.detectors.registry import load

        judge = load(surrogate)
        sim = surrogate_config(det, plan).to_dict()
        target = str(surrogate)
    elif knowledge == "white":
        judge, sim, target = det, calibration_sim(det, name), name
    else:
        raise ValueError(f"stealth: only a white or grey box rehearses a plan, not {knowledge!r}")
    tried = []
    for accel in (None, *plan.rehearse):
        cfg = SimConfig.from_dict({**sim, "flights": REHEARSAL_FLIGHTS, "batch_size": REHEARSAL_FLIGHTS,
                                   "duration": plan.duration, "seed": seed,
                                   "attack": _attack(plan, target, "white", margin, accel)})
        flights = simulate(cfg).flights
        rows = envelope(flights, judge.decision_function(flights), float(judge.threshold_), plan.onset, (T,))
        tried.append({"accel": accel, "deviation_median": float(np.median([r[f"deviation_{T:g}"] for r in rows])),
                      "hidden": float(np.mean([r[f"hidden_{T:g}"] for r in rows]))})
    best = max(tried, key=lambda r: r["deviation_median"])        # ties: the first, the fastest push
    return {"accel": best["accel"], "flights": REHEARSAL_FLIGHTS, "seed": seed, "horizon": T, "tried": tried}


def run_stealth(plan: StealthPlan, out: Path, echo: Callable[[str], None] = print,
                profile: str | None = None) -> dict[str, Any]:
    """Every detector of the plan under each knowledge level and margin; results.json and
    report.html in ``out``. ``profile``: the plan's name in ``PROFILES`` (recorded)."""
    from quadformer.detectors import pretrained
    from quadformer.experiments.provenance import provenance as make_provenance
    from quadformer.io import package_versions, write_json
    from quadformer.simulation import simulate

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    black: dict[str, pd.DataFrame] = {}          # the black box's flights per simulation, flown once
    runs, bounds, skipped, start = [], {}, [], time.perf_counter()
    for name in plan.detectors:
        det = pretrained.load(name)
        entry = pretrained.resolve(name)
        surrogate, rehearsals = None, {}
        for knowledge in plan.knowledge:
            if knowledge == "grey" and surrogate is None:
                if learned(det):
                    skipped.append({"detector": name, "knowledge": "grey", "reason": "a network: the attacker "
                                    "would train its own"})
                    echo(f"stealth: {name:20s} grey   not run ({skipped[-1]['reason']})")
                    continue
                t0 = time.perf_counter()
                surrogate_path = out / "surrogates" / f"{name}.json"
                surrogate = fit_surrogate(det, plan, surrogate_path)
                echo(f"stealth: {name:20s} grey   surrogate fitted on the attacker's own flights (airframe "
                     f"{surrogate['model']}): threshold {surrogate['threshold']:.4g} against the vehicle's "
                     f"{float(det.threshold_):.4g} ({time.perf_counter() - t0:.0f} s)")
            for margin, policy in [(m, p) for m in (plan.margins if knowledge in ("white", "grey") else (None,))
                                   for p in plan.policies]:
                planned = None
                if plan.rehearse and knowledge in ("white", "grey"):
                    if (knowledge, margin) not in rehearsals:
                        t0 = time.perf_counter()
                        rehearsals[knowledge, margin] = rehearse(det, name, plan, knowledge, margin,
                                                                 surrogate_path if knowledge == "grey" else None)
                        r = rehearsals[knowledge, margin]
                        echo(f"stealth: {name:20s} {knowledge:5s} margin {margin:g}  rehearsed: " + ", ".join(
                            f"{plan_name(x['accel'])} {x['deviation_median']:.1f} m" for x in r["tried"])
                            + f" unseen by {r['horizon']:g} s; flies {plan_name(r['accel'])} "
                            f"({time.perf_counter() - t0:.0f} s)")
                    planned = rehearsals[knowledge, margin]
                cfg = stealth_config(name, plan, knowledge, margin, det,
                                     surrogate_path if knowledge == "grey" else None,
                                     None if planned is None else planned["accel"])
                key = cfg.to_dict()
                key["attack"].pop("detector")
                key = repr(key)
                t0 = time.perf_counter()
                if policy == "resilient":      # the detector in the loop: flown for it alone
                    flights = simulate(cfg, defence=det).flights
                elif knowledge == "black" and key in black:
                    flights = black[key]
                else:
                    flights = simulate(cfg).flights
                    if knowledge == "black":
                        black[key] = flights
                scores = det.decision_function(flights)
                rows = envelope(flights, scores, float(det.threshold_), plan.onset, plan.horizons)
                set_name = entry.set.name
                if set_name not in bounds:
                    bounds[set_name] = physical_bound(cfg, plan.horizons)
                summary = summarise(rows, plan.horizons)
                runs.append({"detector": name, "set": set_name, "method": entry.method, "knowledge": knowledge,
                             "margin": margin, "policy": policy, "threshold": float(det.threshold_),
                             "summary": summary,
                             "flights": rows, "seconds": round(time.perf_counter() - t0, 1),
                             **({"surrogate": surrogate} if knowledge == "grey" else {}),
                             **({"rehearsal": planned} if planned is not None else {}),
                             **({"headings": plan.headings} if knowledge != "black" and plan.headings > 1 else {})})
                T = max(plan.horizons)
                if policy == "resilient":
                    said = (f"resilient GPS: deviation reached by {T:g} s: median "
                            f"{summary[f'reached_median_{T:g}']:.1f} m, worst {summary[f'reached_worst_{T:g}']:.1f} m; "
                            f"GPS fused {summary['fused_after_onset']:.0%} of the attack")
                else:
                    said = (f"deviation unseen by {T:g} s: median {summary[f'deviation_median_{T:g}']:.1f} m, worst "
                            f"{summary[f'deviation_worst_{T:g}']:.1f} m; hidden {summary[f'hidden_{T:g}']:.0%}")
                if summary["at_threshold"] >= CEILING_SHARE:
                    said += (f"; the score sat at its threshold on {summary['at_threshold']:.0%} of the attack's steps "
                             "(a ceiling: it cannot alarm there)")
                echo(f"stealth: {name:20s} {knowledge:5s}" + (f" margin {margin:g}" if margin else " " * 11)
                     + f"  {said} (bound {bounds[set_name][f'{T:g}']:.1f} m; {time.perf_counter() - t0:.0f} s)")
    results = {"benchmark": "stealth", "plan": asdict(plan), "bound_z": BOUND_Z, "bounds": bounds, "runs": runs,
               "not_run": skipped,
               "seconds": round(time.perf_counter() - start, 1), "versions": package_versions(),
               "provenance": make_provenance({"dataset": plan.seed}, profile)}
    write_json(out / "results.json", results)
    write_stealth_report(results, out / "report.html")
    return results


__all__ = ["HORIZONS", "POLICIES", "PROFILES", "REHEARSAL_FLIGHTS", "REHEARSAL_SEED", "REHEARSE", "SURROGATE_FLIGHTS",
           "StealthPlan", "calibration_sim", "fit_surrogate", "learned", "rehearse", "run_stealth", "stealth_config",
           "surrogate_config"]
