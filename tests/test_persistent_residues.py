"""Persistent residues (estimator/reference.py): the evidence of a small or slow GPS spoof
lasts as long as the spoof, where the main filter's innovation fades within seconds.

The closed-loop scenarios fly the same flights (same seeds) twice in one batch, attacked and
clean: before the onset both copies are identical, and the clean copies give the levels a
feature reaches without an attack (its 99th percentile over every clean step after the first
5 s). The attack then has to stay above that level for its whole duration after a stated
settling time, judged on the median of each 2 s segment (10 steps: single steps of any
residue are noisy; a detector reads windows).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from quadformer.config import AttackConfig, EKFConfig, GPSConfig, IMUConfig, SimConfig, VIOConfig
from quadformer.estimator.eskf import init_state, noise_model
from quadformer.estimator.reference import GpsFreeReference, ReferenceConfig
from quadformer.estimator.schema import PERSISTENT, groups_for
from quadformer.simulation.closed_loop import simulate_groups

FLIGHTS = np.array([0, 1, 2, 0, 1, 2])
ATTACKED = np.array([True, True, True, False, False, False])
ONSET, DURATION = 10.0, 16.0     # s
CLEAN_FROM = 50                  # clean levels from step 50 (5 s) on
SEGMENT = 20                     # steps (2 s)


def _pairs(*attacks: AttackConfig, sensors: str = "gps+imu+vio", duration: float = 28.0,
           gps: GPSConfig = GPSConfig()):
    """Each attack's flights, attacked and clean copies, all flown in one batch (each equals its
    batch flown alone)."""
    cfgs = [SimConfig(model="I", noise="gaussian", flights=3, duration=duration, seed=5, sensors=sensors,
                      attack=a, gps=gps) for a in attacks]
    return simulate_groups([(c, FLIGHTS, ATTACKED) for c in cfgs])


OFFSET = AttackConfig(kind="bias", onset=(ONSET, ONSET), duration=(DURATION, DURATION), magnitude=(1.0, 1.0),
                      fraction=1.0, axes="xy")
DRIFT = AttackConfig(kind="ramp", onset=(ONSET, ONSET), duration=(DURATION, DURATION), rate=(0.05, 0.05),
                     fraction=1.0)


@pytest.fixture(scope="module")
def flown():
    """A 1 m position offset in the horizontal plane and a 0.05 m/s drift with the matching
    velocity (a coordinated ramp); the simulated receiver's own error wanders (Gauss-Markov,
    0.5 m, 30 s)."""
    return _pairs(OFFSET, DRIFT)


@pytest.fixture(scope="module")
def bias(flown):
    return flown[0]


@pytest.fixture(scope="module")
def white_bias():
    """The offset seen by a receiver whose error is white (no slowly wandering part)."""
    return _pairs(OFFSET, gps=GPSConfig(gm_std=0.0))[0]


@pytest.fixture(scope="module")
def drift(flown):
    return flown[1]


def _segments(r, magnitude, settle: float) -> tuple[np.ndarray, float]:
    """Median of ``magnitude`` over each 2 s segment of the attack after ``settle`` seconds
    (attacked flights x segments), and the clean copies' 99th percentile."""
    m = magnitude(r)
    clean = np.quantile(m[3:, CLEAN_FROM:], 0.99)
    meds = []
    for i in range(3):
        on = np.flatnonzero(r["label"][i])
        assert len(on) == round(DURATION * 10)
        x = m[i, on[0] + round(settle * 10):on[-1] + 1]
        meds.append([np.median(x[s:s + SEGMENT]) for s in range(0, len(x) - SEGMENT + 1, SEGMENT)])
    return np.array(meds), clean


def _ref_offset(r):
    """Horizontal GPS minus reference since the anchor, m."""
    return np.linalg.norm(r["res_ref_d"][..., :2], axis=-1)


def _ref_velocity(r):
    return np.linalg.norm(r["res_ref_vmean"][..., :2], axis=-1)


def _age(r):
    return r["res_ref_age"][..., 0]


def _gps_innovation(r):
    return np.linalg.norm(r["res_gps_w"], axis=-1)


def test_the_attacked_and_clean_copies_agree_before_the_onset(bias):
    before = round(ONSET * 10) - 1
    for g in PERSISTENT:
        assert np.array_equal(bias[g][:3, :before], bias[g][3:, :before]), g


def test_a_1m_offset_stays_in_the_reference_difference_for_the_whole_attack(white_bias):
    """Receiver error white: settling 2 s (the smoothing's time constant twice), then every 2 s
    segment of the offset's GPS minus reference is above the clean flights' 99th percentile. The
    main filter's whitened GPS innovation has fallen back under its clean level 4 s after the
    onset and stays there."""
    meds, clean = _segments(white_bias, _ref_offset, settle=2.0)
    assert (meds > clean).all(), (meds / clean).round(2)
    gps, gps_clean = _segments(white_bias, _gps_innovation, settle=4.0)
    assert (gps < gps_clean).all(), (gps / gps_clean).round(2)


def test_the_anchor_holds_a_1m_offset_while_the_receiver_error_wanders(bias):
    """Receiver error wandering (0.5 m, 30 s): after 10 s a 1 m offset is about 2 sigma of what
    the receiver does by itself, so its size alone cannot stay above clean levels; the anchor
    does not follow it (its age grows by a step every step from 2 s after the onset to the
    end) and the age is above every clean flight's 99th percentile from 8 s after the onset to
    the end. The GPS innovation is back under its clean level from 4 s on."""
    for i in range(3):
        on = np.flatnonzero(bias["label"][i])
        age = bias["res_ref_age"][i, on[0] + 20:on[-1] + 1, 0]
        assert np.allclose(np.diff(age), 0.1), i
    meds, clean = _segments(bias, _age, settle=8.0)
    assert (meds > clean).all(), (meds / clean).round(2)
    gps, gps_clean = _segments(bias, _gps_innovation, settle=4.0)
    assert (gps < gps_clean).all(), (gps / gps_clean).round(2)


def test_a_drift_of_5cm_per_second_stays_in_the_mean_velocity_difference(drift):
    """Settling 10 s (the 10 s averaging reaching two thirds of its level; 0.05 m/s is close to
    what GPS velocity noise and the VIO reference leave after averaging). The GPS innovation
    never leaves its clean level."""
    meds, clean = _segments(drift, _ref_velocity, settle=10.0)
    assert (meds > clean).all(), (meds / clean).round(2)
    gps, gps_clean = _segments(drift, _gps_innovation, settle=0.0)
    assert (gps < gps_clean).all(), (gps / gps_clean).round(2)


def _still_vehicle(steps_per_gps=10, gps_rate=10.0, seconds=40.0, onset=10.0, offset=None, drift=None,
                   matched=True, seed=0, vio=True, accel_error=0.0, P0=0.01):
    """A hovering vehicle: IMU with the specific force of hover, VIO velocity zero with noise (or
    no VIO), and GPS with white noise and, from ``onset``, a constant ``offset`` (m) or a
    ``drift`` (m/s) along x, with the matching velocity when ``matched``. ``accel_error``
    (m/s^2, along x) is an error of the specific force the reference integrates; the main
    filter's state stays at rest with covariance ``P0`` (what a reset hands over). Returns the
    residues per GPS step and, under ``resets``, the steps at which the reference was reset."""
    rng = np.random.default_rng(seed)
    sim = SimConfig()
    nm = noise_model(IMUConfig(), GPSConfig(), VIOConfig(), EKFConfig(), 100.0)
    dt = 1.0 / (steps_per_gps * gps_rate)
    ekf = init_state(torch.zeros(1, 3), torch.zeros(1, 3), torch.tensor([[0.0, 0.0, 0.0, 1.0]]),
                     torch.zeros(1, 3), torch.zeros(1, 3), torch.eye(15).unsqueeze(0) * P0)
    ref = GpsFreeReference(ekf, nm, gps_rate, ("vio",) if vio else ())
    f = torch.tensor([[accel_error, 0.0, 9.81]], dtype=torch.float64)
    rows, resets = [], []
    for j in range(int(seconds * gps_rate)):
        for k in range(steps_per_gps):
            ref.predict(ekf, f, dt)
            if vio and k % 5 == 4:
                ref.vio(torch.from_numpy(rng.normal(0.0, sim.vio.vel_std, (1, 3))))
        t = (j + 1) / gps_rate
        pos = rng.normal(0.0, sim.gps.pos_std_h, (1, 3))
        vel = rng.normal(0.0, sim.gps.vel_std, (1, 3))
        if t >= onset:
            if offset is not None:
                pos[0, 0] += offset
            if drift is not None:
                pos[0, 0] += drift * (t - onset)
                vel[0, 0] += drift if matched else 0.0
        rows.append({k: v.numpy()[0] for k, v in ref.on_gps(torch.from_numpy(pos), torch.from_numpy(vel)).items()})
        drop = ref.drop.clone()
        ref.anchor(ekf)
        if not torch.equal(drop, ref.drop):
            resets.append(j)
    return {**{k: np.stack([r[k] for r in rows]) for k in rows[0]}, "resets": np.array(resets)}


def test_reanchoring_never_absorbs_an_offset_while_it_lasts():
    """GPS that agrees lets the anchor follow 3 s behind (age 3 s); a 1 m offset freezes it for
    as long as it lasts (30 s here), so the offset stays in ``res_ref_w``; a clean run keeps
    following."""
    clean = _still_vehicle(offset=None)
    assert np.allclose(clean["res_ref_age"][100:, 0], 3.1)
    out = _still_vehicle(offset=1.0)
    age = out["res_ref_age"][:, 0]
    assert np.allclose(np.diff(age[110:]), 0.1)            # frozen from 1 s after the onset to the end
    w = out["res_ref_w"][:, 0]
    assert (w[120:] > 1.5).all() and (np.abs(clean["res_ref_w"][100:, 0]) < 1.5).mean() > 0.85


def test_the_mean_velocity_difference_holds_a_drift_the_position_check_lets_pass():
    """A 0.05 m/s drift with its velocity is slower than the position check: the anchor keeps
    following. The reference's velocity (VIO's) does not drift, so the mean velocity difference
    holds it: above the clean run's 99th percentile on at least 95% of the steps from 15 s after
    the onset to the end (the same noise draws, clean and attacked)."""
    clean = np.abs(_still_vehicle()["res_ref_vmean"][100:, 0])
    out = _still_vehicle(drift=0.05)["res_ref_vmean"][250:, 0]
    assert (out > np.quantile(clean, 0.99)).mean() > 0.95


def test_without_camera_a_reset_of_the_reference_raises_no_velocity_alarm():
    """Without VIO the reference's horizontal state drifts (here with a 0.05 m/s^2 error of the
    specific force) and is reset to the main filter every few seconds while GPS agrees. The
    10-s mean velocity difference carries the errors averaged before a reset; whitened by the
    reset reference's small variance alone they read as a coordinated drift at every reset (11
    on this clean run before the fix; an ArduPilot SITL log on the ground raised a `chi2-vref`
    alert every 5.6 s). Whitened by what the reset shifted in, they stay within the noise."""
    out = _still_vehicle(vio=False, seconds=60.0, onset=1e9, accel_error=0.05, P0=1e-3)
    assert len(out["resets"]) >= 5                          # the reference was reset, repeatedly
    assert np.abs(out["res_ref_vmean"]).max() < 3.0


def test_a_position_spoof_without_its_velocity_stays_in_gps_velocity_against_position():
    """A drift of the position alone (0.5 m/s, velocity honest) keeps ``res_gps_pv`` above the
    clean run's 99th percentile on at least 80% of the steps from one horizon (5 s) after the
    onset to the end; the same drift with its velocity on under 5%."""
    level = np.quantile(np.abs(_still_vehicle()["res_gps_pv"][60:, 0]), 0.99)
    out = np.abs(_still_vehicle(drift=0.5, matched=False)["res_gps_pv"][150:, 0])
    assert (out > level).mean() > 0.8
    matched = np.abs(_still_vehicle(drift=0.5)["res_gps_pv"][150:, 0])
    assert (matched > level).mean() < 0.05


def test_without_camera_the_features_are_produced_and_finite():
    (r,) = _pairs(AttackConfig(kind="bias", onset=(3.0, 3.0), duration=(3.0, 3.0), magnitude=(1.0, 1.0),
                               fraction=1.0), sensors="gps+imu+mag+baro", duration=8.0)
    names = [g.name for g in groups_for("gps+imu+mag+baro")]
    for g in PERSISTENT:
        assert g in names and g in r, g
        assert np.isfinite(r[g]).all(), g
    # the reference holds height with the barometer: the vertical comparison keeps a finite scale
    assert np.abs(r["res_ref_w"][3:, 20:, 2]).max() < 10.0


def test_bad_reference_settings_name_the_field():
    with pytest.raises(ValueError, match="reference.smooth_tau"):
        ReferenceConfig(smooth_tau=0.0)
    with pytest.raises(ValueError, match="reference.horizons"):
        ReferenceConfig(horizons=(5.0,))
    with pytest.raises(ValueError, match="release_k"):
        ReferenceConfig(agree_k=1.0, release_k=2.0)
    with pytest.raises(ValueError, match="gps_rate_hz"):
        nm = noise_model(IMUConfig(), GPSConfig(), VIOConfig(), EKFConfig(), 100.0)
        ekf = init_state(torch.zeros(1, 3), torch.zeros(1, 3), torch.tensor([[0.0, 0.0, 0.0, 1.0]]),
                         torch.zeros(1, 3), torch.zeros(1, 3), torch.eye(15).unsqueeze(0))
        GpsFreeReference(ekf, nm, 0.0)
