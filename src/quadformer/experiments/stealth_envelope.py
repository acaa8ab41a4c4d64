"""What a stealthy attack reached: the envelope of a detector, and the physical bound beside it
(the stealth benchmark, ``experiments.stealth``).

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

from typing import Any

import numpy as np
import pandas as pd

from quadformer.config import SimConfig

#: the bound's standard deviations: one-sided, a false alarm in about 740 independent tests
BOUND_Z = 3.0
#: the share of an attack's steps scored at the threshold itself from which a run is said to ride
#: the detector's ceiling (``envelope``'s ``at_threshold``)
CEILING_SHARE = 0.05

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


__all__ = ["BOUND_Z", "CEILING_SHARE", "envelope", "physical_bound", "summarise"]
