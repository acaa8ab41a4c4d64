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
offline ones) at its shipped false-alarm-budget threshold. Under the ``resilient`` policy
(``policies``) its online alarms also act in the loop: GPS leaves the fusion on an alarm and comes
back once trustworthy (``resilience.Admission``), and ``reached`` is the deviation the attack
achieves by each horizon, alarm or not. The deviation is the vehicle's
horizontal estimation error |estimate - truth|: flying its mission on the estimate, the vehicle
is that far from where it believes it is. For each horizon T after the onset: the largest
deviation reached before the first alarm within [onset, onset + T) (``deviation``: the envelope),
and whether no alarm came by then (``hidden``); median and worst over the flights. Beside it,
``deviation_at_alarm``: where the vehicle was when the alarm came.

The physical bound (``physical_bound``): the deviation that no test of GPS against the sensors'
GPS-free evidence can tell from the sensors' own errors at ``BOUND_Z`` standard deviations, T
seconds after the onset. Over T, GPS minus the GPS-free reference changes by the reference's own
error growth (its horizontal position variance propagated from a converged start with the
filter's configuration: the IMU, and VIO velocity or nothing horizontal without a camera) and
by the change of the receiver's slowly varying error (its Gauss-Markov part, ``gps.gm_std`` and
``gps.gm_tau``: 2 gm_std^2 (1 - exp(-T / gm_tau))); the fix's white noise averages out over
the fixes of T seconds and is left out. An attacker whose deviation stays under it is
undetectable on these sensors; a detector whose envelope is far above it leaves room an
attacker uses. Each envelope reads as a ratio to it.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pandas as pd

from quadformer.config import KNOWLEDGE, MAX_HEADINGS, MODELS, SimConfig
from quadformer.report.stealth import plan_name, write_stealth_report

HORIZONS = (10.0, 30.0, 60.0, 120.0)
#: the bound's standard deviations: one-sided, a false alarm in about 740 independent tests
BOUND_Z = 3.0
#: the GPS policies a stealth run flies under (``StealthPlan.policies``)
POLICIES = ("none", "resilient")
#: the grey-box attacker's own clean flights: half fit its surrogate, half set its threshold
SURROGATE_FLIGHTS = 6
#: added to the plan's seed for the attacker's own flights (none of them is a flight it attacks)
SURROGATE_SEED = 7919
#: the flights an attacker rehearses each of its plans on, and the seed added for them
REHEARSAL_FLIGHTS = 2
REHEARSAL_SEED = 104729
#: the share of an attack's steps scored at the threshold itself from which a run is said to ride
#: the detector's ceiling (``envelope``'s ``at_threshold``)
CEILING_SHARE = 0.05
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
    attack = {"kind": "stealthy", "detector": detector, "knowledge": knowledge, "fraction": 1.0,
              "onset": (plan.onset, plan.onset), "rate": (plan.rate, plan.rate), "accel": (plan.accel, plan.accel)}
    if knowledge in ("white", "grey"):
        attack["margin"] = margin
        if plan.headings > 1:
            attack["headings"] = plan.headings
        if plan_accel is not None:
            attack["plan_accel"] = plan_accel
    if knowledge == "grey":
        if surrogate is None:
            raise ValueError(f"stealth: a grey-box attack on {detector} needs its surrogate (fit_surrogate)")
        attack["surrogate"] = str(surrogate)
    sim["attack"] = attack
    return SimConfig.from_dict(sim)


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
        attack = {"kind": "stealthy", "detector": target, "knowledge": "white", "margin": margin, "fraction": 1.0,
                  "onset": (plan.onset, plan.onset), "rate": (plan.rate, plan.rate),
                  "accel": (plan.accel, plan.accel), **({} if accel is None else {"plan_accel": accel})}
        cfg = SimConfig.from_dict({**sim, "flights": REHEARSAL_FLIGHTS, "batch_size": REHEARSAL_FLIGHTS,
                                   "duration": plan.duration, "seed": seed, "attack": attack})
        flights = simulate(cfg).flights
        rows = envelope(flights, judge.decision_function(flights), float(judge.threshold_), plan.onset, (T,))
        tried.append({"accel": accel, "deviation_median": float(np.median([r[f"deviation_{T:g}"] for r in rows])),
                      "hidden": float(np.mean([r[f"hidden_{T:g}"] for r in rows]))})
    best = max(tried, key=lambda r: r["deviation_median"])        # ties: the first, the fastest push
    return {"accel": best["accel"], "flights": REHEARSAL_FLIGHTS, "seed": seed, "horizon": T, "tried": tried}


def envelope(flights: pd.DataFrame, scores: np.ndarray, threshold: float, onset: float,
             horizons: tuple[float, ...]) -> list[dict[str, Any]]:
    """Per flight: the first alarm at or after the onset, the deviation when it came, and per
    horizon the largest deviation before it (and whether none came by then) and the largest
    reached, alarm or not (``reached``: under the resilient policy, what the attack achieves
    with the defence acting); with a ``gps_fused`` column, the share of fixes fused after the
    onset. ``at_threshold``: the share of the steps after the onset whose score is the threshold
    itself: a score held at a ceiling that its threshold was calibrated on never passes it (the
    detector cannot alarm there, whatever the attack)."""
    out = []
    scores = np.asarray(scores, dtype=float)
    if len(scores) != len(flights):
        raise ValueError(f"envelope: {len(scores)} scores for {len(flights)} rows")
    flights = flights.reset_index(drop=True)            # row i scored scores[i]
    for fid, g in flights.groupby("flight_id", sort=True):
        t = g.t.to_numpy()
        s = scores[g.index.to_numpy()]
        dev = np.hypot(g.est_pos_x - g.true_pos_x, g.est_pos_y - g.true_pos_y).to_numpy()
        after = t >= onset - 1e-9
        alarm = np.flatnonzero(after & (s > threshold))
        t_alarm = float(t[alarm[0]]) if len(alarm) else None
        row: dict[str, Any] = {"flight": int(fid), "alarm_before_onset": bool((s[~after] > threshold).any()),
                               "first_alarm_s": None if t_alarm is None else t_alarm - onset,
                               "deviation_at_alarm": None if t_alarm is None else float(dev[alarm[0]]),
                               "offset_end": float(np.hypot(g.atk_d_x, g.atk_d_y).to_numpy()[-1]),
                               "at_threshold": float(np.mean(s[after] == threshold)) if after.any() else 0.0}
        for T in horizons:
            within = after & (t < onset + T)
            inside = within & (t < (np.inf if t_alarm is None else t_alarm))
            row[f"deviation_{T:g}"] = float(dev[inside].max()) if inside.any() else 0.0
            row[f"reached_{T:g}"] = float(dev[within].max()) if within.any() else 0.0
            row[f"hidden_{T:g}"] = t_alarm is None or t_alarm >= onset + T
        if "gps_fused" in g:
            row["fused_after_onset"] = float(g.gps_fused.to_numpy()[after].mean()) if after.any() else 1.0
        out.append(row)
    return out


def physical_bound(cfg: SimConfig, horizons: tuple[float, ...], z: float = BOUND_Z) -> dict[str, float]:
    """``z`` x the std of the change of GPS minus the GPS-free reference over T seconds, per
    horizon T (keys as ``f"{T:g}"``): the reference's horizontal position variance growth without
    GPS from the filter's converged start (IMU; VIO velocity where the configuration has it),
    plus the change of the receiver's Gauss-Markov error over T."""
    import torch

    from quadformer.estimator.eskf import init_state, noise_model
    from quadformer.estimator.reference import GpsFreeReference
    from quadformer.estimator.residues import AIDING
    from quadformer.simulation.closed_loop import initial_std

    nm = noise_model(cfg.imu, cfg.gps, cfg.vio, cfg.ekf, 1.0 / cfg.dt, cfg.mag, cfg.baro)
    std0 = initial_std(cfg)
    zero = torch.zeros(1, 3, dtype=torch.float64)
    ekf = init_state(zero, zero, torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=torch.float64), zero, zero,
                     torch.diag(torch.from_numpy(std0 ** 2))[None])
    aiding = tuple(a for a in AIDING if cfg.has(a))
    ref = GpsFreeReference(ekf, nm, cfg.gps.rate_hz, aiding)
    start = float(ref.C[0, 0, 0, 0])
    g = cfg.gps
    out, steps = {}, 0
    for T in sorted(horizons):
        while steps * cfg.dt < T - 1e-9:
            ref.predict(ekf, torch.tensor([[0.0, 0.0, 9.81]], dtype=torch.float64), cfg.dt)
            steps += 1
            if "vio" in aiding and steps % cfg.steps_per_vio == 0:
                ref.vio(torch.zeros(1, 3, dtype=torch.float64))
        slow = 2.0 * g.gm_std ** 2 * (1.0 - np.exp(-T / g.gm_tau))
        out[f"{T:g}"] = z * float(np.sqrt(max(float(ref.C[0, 0, 0, 0]) - start, 0.0) + slow))
    return out


def summarise(rows: list[dict[str, Any]], horizons: tuple[float, ...]) -> dict[str, Any]:
    out: dict[str, Any] = {"flights": len(rows)}
    for T in horizons:
        dev = np.array([r[f"deviation_{T:g}"] for r in rows])
        out[f"deviation_median_{T:g}"] = float(np.median(dev))
        out[f"deviation_worst_{T:g}"] = float(dev.max())
        out[f"hidden_{T:g}"] = float(np.mean([r[f"hidden_{T:g}"] for r in rows]))
        reached = np.array([r[f"reached_{T:g}"] for r in rows])
        out[f"reached_median_{T:g}"] = float(np.median(reached))
        out[f"reached_worst_{T:g}"] = float(reached.max())
    if rows and "fused_after_onset" in rows[0]:
        out["fused_after_onset"] = float(np.mean([r["fused_after_onset"] for r in rows]))
    alarmed = [r["deviation_at_alarm"] for r in rows if r["deviation_at_alarm"] is not None]
    out["alarmed"] = len(alarmed)
    out["deviation_at_alarm_median"] = float(np.median(alarmed)) if alarmed else None
    out["alarm_before_onset"] = int(sum(r["alarm_before_onset"] for r in rows))
    out["at_threshold"] = float(np.mean([r.get("at_threshold", 0.0) for r in rows])) if rows else 0.0
    return out


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


__all__ = ["BOUND_Z", "CEILING_SHARE", "HORIZONS", "POLICIES", "PROFILES", "REHEARSAL_FLIGHTS", "REHEARSAL_SEED",
           "SURROGATE_FLIGHTS", "StealthPlan", "envelope", "fit_surrogate", "learned", "physical_bound", "rehearse",
           "run_stealth", "stealth_config", "summarise", "surrogate_config"]
