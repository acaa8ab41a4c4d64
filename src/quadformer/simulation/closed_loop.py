"""The closed loop for one batch of flights.

At every 100 Hz step: the SE(3) controller flies on the EKF estimate, rotorpy integrates
the vehicle in its wind, the IMU samples the motion and the EKF propagates. The configured
aiding sensors update the EKF at their rates, in the order VIO (20 Hz), magnetometer heading
(50 Hz), barometric height (25 Hz); at 10 Hz the GPS fix (honest, then attacked) updates it
and the innovation statistics are recorded as residues. Beside the filter, the GPS-free
reference (``estimator.reference``) propagates with the same IMU samples and takes the same VIO
and barometer samples, never GPS; at each fix it gives the persistent residues. A spoofed fix
therefore moves the real vehicle. A sensor the configuration leaves out draws nothing and records nothing.

With an ``Admission`` (resilience), each GPS step first computes the innovation for every
flight, lets an online detector score the residues, and fuses the fix only where the
flight's admission policy allows (possibly with inflated noise, a reset or a rollback).
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import replace
from typing import Callable, Sequence

import numpy as np
import roma
import torch

from quadformer.attacks import concat_attacks, sample_attacks
from quadformer.config import STEALTH, SimConfig
from quadformer.estimator.eskf import (
    baro_update,
    gps_update,
    init_state,
    mag_update,
    nees,
    noise_model,
    predict,
    reset_to_gps,
    vio_update,
)
from quadformer.estimator.reference import GpsFreeReference
from quadformer.estimator.residues import AIDING, ResidueTracker
from quadformer.estimator.schema import as_columns, groups_for
from quadformer.geometry import exp_quat
from quadformer.missions import sample_missions
from quadformer.plant import DrydenWind, Plant, concat_wind, sample_wind
from quadformer.resilience.step import OnlineStep
from quadformer.rng import Stream, batch_generators
from quadformer.sensors import GPS, IMU, VIO, Barometer, ChunkedNoise, Magnetometer
from quadformer.simulation.stealth import stealthy_attacker


def records(cfg: SimConfig) -> dict[str, int]:
    """Recorded per GPS step: the widths of the schema's groups of the configuration's
    sensors (the reference is evaluated after the flight)."""
    return {g.name: g.width for g in groups_for(cfg.sensors) if g.name != "ref_pos"}


def initial_std(cfg: SimConfig) -> np.ndarray:
    """The filter's initial error std (15,): position, velocity, attitude (rad), accelerometer and
    gyro biases: the filter has converged on the ground before the mission."""
    e = cfg.ekf
    return np.array([e.init_pos_std] * 3 + [e.init_vel_std] * 3 + [np.deg2rad(e.init_att_std_deg)] * 3
                    + [cfg.imu.accel_bias_std] * 3 + [cfg.imu.gyro_bias_std] * 3)


class BatchResult(dict):
    """Arrays of one batch: ``records(cfg)`` entries (B, n_gps, k) plus labels and scenario info."""


def simulate_batch(cfg: SimConfig, flights: np.ndarray, attacked: np.ndarray,
                   progress: Callable[[float], None] | None = None, record_nees: bool = False,
                   record_sensors: bool = False, admission=None, stream=None) -> BatchResult:
    """Simulate flights ``flights`` (indices into the dataset) of ``cfg`` together.

    record_nees: also the filter's NEES per GPS step (consistency checks); record_sensors:
    also the raw IMU, (attacked) GPS and configured VIO, magnetometer and barometer streams
    and the initial filter state, which ``estimator.replay.run_ekf`` can process on their own,
    and at each GPS step the true attitude and the filter's (``true_q``, ``est_q``: xyzw,
    body FLU -> world ENU; with ``true_pos``/``est_pos`` and the velocities, a flight log's
    truth and estimate).

    admission: a ``resilience.Admission`` over the batch's flights (GPS fused per policy);
    stream: a detector's online stream over the batch (``detector.stream(len(flights))``)
    whose alarms drive the ``resilient`` policy. Both add per-step ``admission`` records
    (fused, noise scale, reset, score, alarm, the position correction GPS applied to the
    estimate: the update's, a reset's jump and a rollback together, and the rule that
    re-admitted or excluded GPS at the step: ``Decision.readmit`` / ``Decision.exclude``)."""
    return _simulate([(cfg, np.asarray(flights), np.asarray(attacked))], progress, record_nees, record_sensors,
                     admission, stream)


#: what may differ between configurations flown in one batch (``simulate_groups``)
PER_FLIGHT = ("model", "noise", "attack", "seed", "flights", "batch_size")


def mixable(a: SimConfig, b: SimConfig) -> bool:
    """Whether flights of ``a`` and ``b`` can fly in one batch: the configurations differ
    only in vehicle model, noise shape, attack, seed and size (``PER_FLIGHT``)."""
    da, db = a.to_dict(), b.to_dict()
    return all(da[k] == db[k] for k in da if k not in PER_FLIGHT)


def mixable_families(cfgs: Sequence[SimConfig]) -> list[list[int]]:
    """Indices of ``cfgs`` grouped into families that can fly in one batch (``mixable``), in
    order of first appearance."""
    families: list[list[int]] = []
    for i, c in enumerate(cfgs):
        for fam in families:
            if mixable(cfgs[fam[0]], c):
                fam.append(i)
                break
        else:
            families.append([i])
    return families


def simulate_groups(groups: Sequence[tuple[SimConfig, np.ndarray, np.ndarray]],
                    progress: Callable[[float], None] | None = None, admission=None,
                    stream=None) -> list[BatchResult]:
    """Flights of several configurations in one batch: ``groups`` holds (config, flight
    indices, attacked) per configuration, the configurations ``mixable``. Vehicle model,
    noise shape, attack and seed are per flight, so each group's result equals
    ``simulate_batch(config, flights, attacked)`` of that group alone, bit for bit (flight
    i's data depends only on its configuration, seed and i). Returns one ``BatchResult``
    per group, in order.

    admission, stream: as in ``simulate_batch``, over the whole batch (the groups' flights in
    order); a ``detectors.StreamGroup`` gives each group the stream of its own detector."""
    groups = [(c, np.asarray(f), np.asarray(a, dtype=bool)) for c, f, a in groups]
    if not groups:
        return []
    for c, _, _ in groups[1:]:
        if not mixable(groups[0][0], c):
            raise ValueError("simulate_groups: configurations must differ only in "
                             f"{', '.join(PER_FLIGHT)} to fly in one batch")
    whole = _simulate(groups, progress, admission=admission, stream=stream)
    out, start = [], 0
    B = len(whole["label"])
    for _, f, _ in groups:
        idx = np.arange(start, start + len(f))
        start += len(f)
        part = BatchResult({k: (v if k == "t" else _take(v, idx, B)) for k, v in whole.items()})
        out.append(part)
    return out


def _take(v, idx: np.ndarray, B: int):
    """Rows ``idx`` of a batch's per-flight value (arrays, tensors, dataclasses of them, dicts)."""
    if v is None:
        return None
    if isinstance(v, dict):
        return {k: _take(x, idx, B) for k, x in v.items()}
    if dataclasses.is_dataclass(v) and not isinstance(v, type):
        return dataclasses.replace(v, **{f.name: _take(getattr(v, f.name), idx, B)
                                         for f in dataclasses.fields(v) if f.init})
    if isinstance(v, (np.ndarray, torch.Tensor)) and v.ndim >= 1 and v.shape[0] == B:
        return v[idx]
    return v


def _simulate(groups, progress=None, record_nees=False, record_sensors=False, admission=None, stream=None):
    # no autograd bookkeeping in the loop: about a fifth of the per-step cost, same numbers
    with torch.inference_mode():
        return _simulate_loop(groups, progress, record_nees, record_sensors, admission, stream)


def _simulate_loop(groups, progress, record_nees, record_sensors, admission, stream):
    cfg = groups[0][0]
    flights = np.concatenate([f for _, f, _ in groups])
    B = len(flights)
    single = len(groups) == 1

    def gens(stream_: Stream) -> list[np.random.Generator]:
        return [g for c, f, _ in groups for g in batch_generators(c.seed, f, stream_)]

    def per_flight(values: list) -> list:
        return [v for (_, f, _), v in zip(groups, values) for _ in range(len(f))]

    dt, n_steps, spg, spv, n_gps = cfg.dt, cfg.n_steps, cfg.steps_per_gps, cfg.steps_per_vio, cfg.n_gps
    scn = gens(Stream.SCENARIO)
    scn_parts, start = [], 0
    for _, f, _ in groups:
        scn_parts.append(scn[start:start + len(f)])
        start += len(f)
    missions = sample_missions(scn, cfg.mission, cfg.duration)
    wind = concat_wind([sample_wind(g, c.model) for (c, _, _), g in zip(groups, scn_parts)])
    ba0 = np.stack([g.standard_normal(3) for g in scn]) * cfg.imu.accel_bias_std
    bg0 = np.stack([g.standard_normal(3) for g in scn]) * cfg.imu.gyro_bias_std
    init_err = np.stack([g.standard_normal(9) for g in scn])
    attacks = concat_attacks([sample_attacks(g, c.attack, a, c.duration)
                              for (c, _, a), g in zip(groups, scn_parts)])
    attacker = None
    if any(c.attack.kind == STEALTH for c, _, _ in groups):
        if not single:
            raise ValueError("a stealthy attack flies in a batch of its own configuration (its attacker runs one "
                             "detector over the batch)")
        attacker = stealthy_attacker(cfg, attacks)
    model = cfg.model if single else per_flight([c.model for c, _, _ in groups])
    shape = cfg.noise if single else per_flight([c.noise for c, _, _ in groups])

    p0, v0, _ = (torch.from_numpy(x[:, 0]) for x in missions.evaluate(np.array([0.0])))
    plant = Plant(model, p0.numpy(), v0.numpy())
    dryden = DrydenWind(wind, missions.altitude)
    wind_draws = ChunkedNoise(gens(Stream.WIND), "uniform", 3)
    imu = IMU(cfg.imu, 1.0 / dt, gens(Stream.IMU), ba0, bg0)
    gps = GPS(cfg.gps, shape, gens(Stream.GPS))
    vio = VIO(cfg.vio, shape, gens(Stream.VIO), p0) if cfg.has("vio") else None
    mag = Magnetometer(cfg.mag, shape, gens(Stream.MAG)) if cfg.has("mag") else None
    baro = Barometer(cfg.baro, shape, gens(Stream.BARO)) if cfg.has("baro") else None
    spm, spb = cfg.steps_per_mag, cfg.steps_per_baro
    nm = noise_model(cfg.imu, cfg.gps, cfg.vio, cfg.ekf, 1.0 / dt, cfg.mag, cfg.baro)
    aiding = tuple(a for a in AIDING if cfg.has(a))

    std0 = initial_std(cfg)
    err = torch.from_numpy(init_err * std0[:9])
    q0 = plant.state["q"]
    ekf = init_state(p0 + err[:, 0:3], v0 + err[:, 3:6],
                     roma.quat_product(q0, exp_quat(err[:, 6:9])),
                     torch.zeros(B, 3), torch.zeros(B, 3),
                     torch.diag(torch.from_numpy(std0**2)).repeat(B, 1, 1))

    rec = {k: np.zeros((B, n_gps, n), dtype=np.float64) for k, n in records(cfg).items()}
    label = np.zeros((B, n_gps), dtype=bool)
    nees_rec = np.zeros((B, n_gps)) if record_nees else None
    history = torch.zeros(B, n_gps, 6, dtype=torch.float64)
    zeros_b = torch.zeros(B, dtype=torch.float64)
    rates_est = torch.zeros(B, 3, dtype=torch.float64)
    vio_pos = torch.zeros(B, 3, dtype=torch.float64)
    residues = ResidueTracker(B, cfg.gps.rate_hz, aiding=aiding)
    reference = GpsFreeReference(ekf, nm, cfg.gps.rate_hz, aiding)
    sensors = {"ekf0": ekf, "imu": [], "gps": [], "true_q": [], "est_q": [], **{a: [] for a in aiding}} \
        if record_sensors else None
    block = 100
    ref_block = None
    adm_rec = {k: np.zeros((B, n_gps, *shape), dtype=dt_) for k, dt_, shape in
               (("fused", bool, ()), ("std_scale", float, ()), ("reset", bool, ()), ("score", float, ()),
                ("alarm", bool, ()), ("correction", float, (3,)), ("readmit", np.int8, ()),
                ("exclude", np.int8, ()))} if admission is not None else None
    step = OnlineStep(stream, admission) if admission is not None else None

    for k in range(n_steps):
        if k % block == 0:
            tb = (k + np.arange(block)) * dt
            ref_block = [torch.from_numpy(x) for x in missions.evaluate(tb)]
        i = k % block
        ref = {"x": ref_block[0][:, i], "x_dot": ref_block[1][:, i], "x_ddot": ref_block[2][:, i],
               "yaw": zeros_b, "yaw_dot": zeros_b}
        est = {"x": ekf.p, "v": ekf.v, "q": ekf.q, "w": rates_est}
        ctrl = plant.control(est, ref)
        w_vec = dryden.update(dt, wind_draws.next())
        v_prev, w_prev, q_prev = plant.state["v"], plant.state["w"], plant.state["q"]
        state = plant.step(ctrl, w_vec, dt)

        acc = (state["v"] - v_prev) / dt
        rates = 0.5 * (w_prev + state["w"])
        q_mid = roma.quat_normalize(q_prev + torch.sign((q_prev * state["q"]).sum(-1, keepdim=True)) * state["q"])
        accel, gyro = imu.measure(acc, rates, roma.unitquat_to_rotmat(q_mid))
        if sensors is not None:
            sensors["imu"].append(torch.cat([accel, gyro], -1))
        reference.predict(ekf, accel, dt)
        ekf = predict(ekf, accel, gyro, dt, nm)
        rates_est = gyro - ekf.bg

        if vio is not None and (k + 1) % spv == 0:
            v_m, q_m, vio_pos = vio.measure(state["x"], state["v"], state["q"])
            if sensors is not None:
                sensors["vio"].append(torch.cat([v_m, q_m], -1))
            ekf, inn = vio_update(ekf, v_m, q_m, nm)
            residues.on_vio(inn)
            reference.vio(v_m)

        if mag is not None and (k + 1) % spm == 0:
            field = mag.measure(roma.unitquat_to_rotmat(state["q"]))
            if sensors is not None:
                sensors["mag"].append(field)
            ekf, inn = mag_update(ekf, field, nm)
            residues.on_mag(inn)

        if baro is not None and (k + 1) % spb == 0:
            height = baro.measure(state["x"])
            if sensors is not None:
                sensors["baro"].append(height)
            ekf, inn = baro_update(ekf, height, nm)
            residues.on_baro(inn)
            reference.baro(height)

        if (k + 1) % spg == 0:
            j = (k + 1) // spg - 1
            t = (k + 1) * dt
            pos_h, vel_h = gps.measure(state["x"], state["v"])
            history[:, j] = torch.cat([pos_h, vel_h], -1)
            if attacker is None:
                pos_g, vel_g, active, d_pos, _ = attacks.apply(t, j, pos_h, vel_h, history, cfg.gps.rate_hz)
            else:
                def trial(pos_c, vel_c, ekf=ekf):     # what the filter would make of candidate fixes
                    _, inn_c = gps_update(ekf, pos_c, vel_c, nm)
                    res_c = {**copy.deepcopy(residues).on_gps(inn_c), **copy.deepcopy(reference).on_gps(pos_c, vel_c)}
                    return as_columns({**res_c, "gps_pos": pos_c, "gps_vel": vel_c})

                pos_g, vel_g, active, d_pos = attacker.fixes(t, pos_h, vel_h, trial)
            if sensors is not None:
                sensors["gps"].append(torch.cat([pos_g, vel_g], -1))
            proposed, inn = gps_update(ekf, pos_g, vel_g, nm)
            res = {**residues.on_gps(inn), **reference.on_gps(pos_g, vel_g)}
            if attacker is not None:
                attacker.observe(as_columns({**res, "gps_pos": pos_g, "gps_vel": vel_g}))
            if admission is None:
                ekf = proposed
            else:
                ekf = _admit(ekf, proposed, inn, res, pos_g, vel_g, nm, np.asarray(active), step, t,
                             residues, adm_rec, j)
            reference.anchor(ekf)
            if sensors is not None:
                sensors["true_q"].append(state["q"])
                sensors["est_q"].append(ekf.q)
            label[:, j] = active
            for name, val in (
                ("true_pos", state["x"]), ("true_vel", state["v"]), ("est_pos", ekf.p), ("est_vel", ekf.v),
                ("gps_pos", pos_g), ("gps_vel", vel_g), *((("vio_pos", vio_pos),) if vio is not None else ()),
                ("wind", w_vec), *res.items(),
            ):
                rec[name][:, j] = val.numpy()
            rec["atk_d"][:, j] = d_pos
            if nees_rec is not None:
                nees_rec[:, j] = nees(ekf, state["x"], state["v"], state["q"]).numpy()
            if progress is not None and (k + 1) % int(round(1.0 / dt)) == 0:
                progress(B)   # one simulated second of B flights

    t_gps = (np.arange(n_gps) + 1) / cfg.gps.rate_hz
    ref_pos = missions.evaluate(t_gps)[0]
    out = BatchResult(rec)
    out.update(flights=np.asarray(flights), t=t_gps, label=label, ref_pos=ref_pos,
               missions=missions, wind_params=wind, attacks=attacks, nees=nees_rec, admission=adm_rec)
    if sensors is not None:
        out["sensors"] = {
            "ekf0": sensors["ekf0"], "noise": nm, "dt": dt,
            "imu_t": (np.arange(n_steps) + 1) * dt, "imu": torch.stack(sensors["imu"], 1),
            "gps_t": t_gps, "gps": torch.stack(sensors["gps"], 1),
            "true_q": torch.stack(sensors["true_q"], 1), "est_q": torch.stack(sensors["est_q"], 1),
        }
        for a, steps in (("vio", spv), ("mag", spm), ("baro", spb)):
            if a in aiding:
                out["sensors"][f"{a}_t"] = (np.arange(len(sensors[a])) + 1) * steps * dt
                out["sensors"][a] = torch.stack(sensors[a], 1)
    return out


def _admit(ekf, proposed, inn, res, pos_g, vel_g, nm, attacked, step, t, residues, rec, j):
    """One GPS step under admission control: the online step scores and decides per flight; apply."""
    fix = {"gps_pos": np.asarray(pos_g, dtype=float), "gps_vel": np.asarray(vel_g, dtype=float)}
    out = step.update(t, {**res, **fix}, attacked)       # the fix as received: detectors that read it (glr)
    score, alarm, dec, admission = out.score, out.alarm, out.decision, step.admission
    scaled = dec.fuse & (dec.std_scale != 1.0)
    if bool(dec.fuse.all()) and not bool(scaled.any()):
        new, dx = proposed, inn.dx
    else:
        new, inn_applied = gps_update(ekf, pos_g, vel_g, nm, mask=torch.from_numpy(dec.fuse),
                                      std_scale=torch.from_numpy(dec.std_scale))
        dx = inn_applied.dx
    applied = dx[:, 0:3]
    if bool(dec.reset.any()):
        jumped = reset_to_gps(new, pos_g, vel_g, nm, torch.from_numpy(dec.reset))
        applied = applied + (jumped.p - new.p)
        new = jumped
    admission.record(applied.numpy())  # what GPS did to the estimate (a later rollback undoes it)
    if bool(dec.rollback.any()):
        rollback = torch.from_numpy(dec.rollback)
        new = replace(new, p=new.p + rollback)
        applied = applied + rollback
    residues.applied(inn.dx[:, 0:3], applied)
    rec["fused"][:, j] = dec.fuse
    rec["std_scale"][:, j] = dec.std_scale
    rec["reset"][:, j] = dec.reset
    rec["score"][:, j] = score
    rec["alarm"][:, j] = alarm
    rec["correction"][:, j] = applied.numpy()
    rec["readmit"][:, j] = dec.readmit
    rec["exclude"][:, j] = dec.exclude
    return new
