"""Part 5: the error-state EKF: reference equivalence, Jacobians, consistency."""

from dataclasses import replace

import numpy as np
import pytest
import roma
import torch
from filterpy.kalman import ExtendedKalmanFilter
from scipy.stats import chi2

from quadformer.config import BaroConfig, EKFConfig, GPSConfig, IMUConfig, MagConfig, SimConfig, VIOConfig
from quadformer.estimator.eskf import (
    BARO_IDX,
    GPS_IDX,
    NoiseModel,
    baro_update,
    gps_update,
    init_state,
    mag_heading,
    mag_update,
    noise_model,
    predict,
    update,
)
from quadformer.simulation.closed_loop import simulate_batch

NM = NoiseModel(accel_std=0.1, gyro_std=0.01, accel_walk=1e-4, gyro_walk=1e-5,
                gps_std=torch.tensor([0.7, 0.7, 1.1, 0.1, 0.1, 0.1], dtype=torch.float64),
                vio_std=torch.tensor([0.05] * 3 + [0.01] * 3, dtype=torch.float64))


def _random_state(seed, B=1):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((B, 15, 15))
    P = A @ A.transpose(0, 2, 1) / 15 + 0.01 * np.eye(15)
    return init_state(rng.standard_normal((B, 3)), rng.standard_normal((B, 3)),
                      torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=torch.float64).repeat(B, 1),
                      0.01 * rng.standard_normal((B, 3)), 0.001 * rng.standard_normal((B, 3)), P), rng


def test_gps_update_matches_filterpy():
    """A reduced case: the GPS update of the error state against filterpy 2.0's EKF."""
    s, rng = _random_state(0)
    z = rng.standard_normal(6)
    r = torch.from_numpy(z - np.concatenate([s.p[0].numpy(), s.v[0].numpy()]))[None]
    new, inn = update(s, r, GPS_IDX, NM.gps_std)

    ref = ExtendedKalmanFilter(dim_x=15, dim_z=6)
    ref.x = np.concatenate([s.p[0], s.v[0], np.zeros(3), s.ba[0], s.bg[0]])
    ref.P = s.P[0].numpy().copy()
    H = np.zeros((6, 15))
    H[np.arange(6), np.arange(6)] = 1.0
    R = np.diag(NM.gps_std.numpy() ** 2)
    ref.update(z, lambda x: H, lambda x: H @ x, R=R)

    assert np.allclose(new.p[0].numpy(), ref.x[0:3], atol=1e-9)
    assert np.allclose(new.v[0].numpy(), ref.x[3:6], atol=1e-9)
    assert np.allclose(roma.unitquat_to_rotvec(new.q)[0].numpy(), ref.x[6:9], atol=1e-9)
    assert np.allclose(new.ba[0].numpy(), ref.x[9:12], atol=1e-9)
    assert np.allclose(new.bg[0].numpy(), ref.x[12:15], atol=1e-9)
    assert np.allclose(new.P[0].numpy(), ref.P, atol=1e-9)
    # whitened innovation and NIS
    assert np.allclose(inn.r[0].numpy(), ref.y, atol=1e-12)
    assert inn.nis[0].item() == pytest.approx(ref.y @ np.linalg.solve(ref.S, ref.y), rel=1e-9)
    assert np.allclose(inn.w[0].numpy(), np.linalg.solve(np.linalg.cholesky(ref.S), ref.y), atol=1e-9)


def test_general_h_update_matches_filterpy():
    """One update with a dense H (3 x 15) against filterpy 2.0's EKF (Joseph form there too)."""
    s, rng = _random_state(4)
    H = rng.standard_normal((3, 15))
    std = np.array([0.3, 0.05, 0.02])
    x0 = np.concatenate([s.p[0], s.v[0], np.zeros(3), s.ba[0], s.bg[0]])   # attitude error 0 at q = identity
    z = H @ x0 + rng.standard_normal(3) * std
    r = torch.from_numpy(z - H @ x0)[None]
    new, inn = update(s, r, torch.from_numpy(H)[None], torch.from_numpy(std))

    ref = ExtendedKalmanFilter(dim_x=15, dim_z=3)
    ref.x = x0.copy()
    ref.P = s.P[0].numpy().copy()
    ref.update(z, lambda x: H, lambda x: H @ x, R=np.diag(std**2))

    got = np.concatenate([new.p[0], new.v[0], roma.unitquat_to_rotvec(new.q)[0], new.ba[0], new.bg[0]])
    np.testing.assert_allclose(got, ref.x, atol=1e-9, rtol=0)
    np.testing.assert_allclose(new.P[0].numpy(), ref.P, atol=1e-9, rtol=0)
    np.testing.assert_allclose(inn.nis[0].item(), ref.y @ np.linalg.solve(ref.S, ref.y), rtol=1e-9)
    np.testing.assert_allclose(inn.w[0].numpy(), np.linalg.solve(np.linalg.cholesky(ref.S), ref.y), atol=1e-9)
    np.testing.assert_allclose(inn.s_std[0].numpy(), np.sqrt(np.diag(ref.S)), atol=1e-12)


@pytest.mark.parametrize("idx", [GPS_IDX, BARO_IDX])
def test_selection_and_general_h_agree(idx):
    """The selection path is the general one with H = the selected rows of I (batch of 3, masked)."""
    s, rng = _random_state(5, B=3)
    m = len(idx)
    r = torch.from_numpy(rng.standard_normal((3, m)))
    std = torch.from_numpy(rng.uniform(0.1, 1.0, (3, m)))
    mask = torch.tensor([True, False, True])
    H = torch.eye(15, dtype=torch.float64)[idx].expand(3, m, 15)
    a, ia = update(s, r, idx, std, mask)
    b, ib = update(s, r, H, std, mask)
    for x, y in ((a.p, b.p), (a.v, b.v), (a.q, b.q), (a.P, b.P), (ia.nis, ib.nis), (ia.w, ib.w), (ia.dx, ib.dx)):
        assert torch.allclose(x, y, atol=1e-12, rtol=0)
    assert torch.equal(b.P[1], s.P[1])


def _level(yaw_deg, B=1):
    rv = torch.tensor([[0.0, 0.0, np.deg2rad(yaw_deg)]], dtype=torch.float64).repeat(B, 1)
    return roma.rotvec_to_unitquat(rv)


MAG_NM = noise_model(IMUConfig(), GPSConfig(), VIOConfig(), EKFConfig(), 100.0, MagConfig(), BaroConfig())


@pytest.mark.parametrize("est, true, error", [(0.0, 10.0, 10.0), (30.0, 20.0, -10.0), (175.0, -175.0, 10.0),
                                              (-175.0, 175.0, -10.0), (-90.0, -80.0, 10.0)])
def test_heading_update_by_hand(est, true, error):
    """Level vehicle, heading off by 10 deg: the innovation is the error, across +-180 deg too,
    and the update turns the estimate towards the truth."""
    P = np.diag([1.0] * 6 + [np.deg2rad(1.0) ** 2, np.deg2rad(1.0) ** 2, np.deg2rad(20.0) ** 2] + [1e-4] * 6)
    s = init_state(np.zeros((1, 3)), np.zeros((1, 3)), _level(est), np.zeros((1, 3)), np.zeros((1, 3)), P[None])
    field = roma.unitquat_to_rotmat(_level(true))[0].T @ MAG_NM.mag_field      # noise-free body field
    new, inn = mag_update(s, field[None], MAG_NM)
    assert inn.r.shape == (1, 1)
    assert inn.r.item() == pytest.approx(np.deg2rad(error), abs=1e-12)
    left = mag_heading(new, field[None], MAG_NM.mag_field)[0].item()
    assert 0 < left / inn.r.item() < 0.05                  # S is dominated by the 20 deg heading std
    # level, heading east: H = (0, B_v / B_h, 1) on the attitude error once turned to the heading
    _, H = mag_heading(s, field[None], MAG_NM.mag_field)
    c, sn = np.cos(np.deg2rad(est)), np.sin(np.deg2rad(est))
    expect = np.array([sn * 0.42 / 0.22, c * 0.42 / 0.22, 1.0])
    np.testing.assert_allclose(H[0, 0, 6:9].numpy(), expect, atol=1e-12)
    assert torch.count_nonzero(H[0, 0, [*range(6), *range(9, 15)]]) == 0


def test_heading_jacobian_matches_finite_differences():
    """Tilted vehicle, field with declination and inclination: H of the heading innovation equals
    its numerical derivative with respect to the attitude error (q_true = q Exp(dtheta))."""
    nm = noise_model(IMUConfig(), GPSConfig(), VIOConfig(), EKFConfig(), 100.0, MagConfig(declination_deg=12.0))
    rng = np.random.default_rng(3)
    q = roma.rotvec_to_unitquat(torch.from_numpy(rng.standard_normal((1, 3)) * 0.6))
    s = init_state(np.zeros((1, 3)), np.zeros((1, 3)), q, np.zeros((1, 3)), np.zeros((1, 3)), np.eye(15)[None])

    def innovation(dth):
        q_true = roma.quat_product(s.q, roma.rotvec_to_unitquat(torch.from_numpy(dth)[None]))
        body = roma.unitquat_to_rotmat(q_true)[0].T @ nm.mag_field
        return mag_heading(s, body[None], nm.mag_field)[0].item()

    eps = 1e-6
    num = [(innovation(eps * e) - innovation(-eps * e)) / (2 * eps) for e in np.eye(3)]
    _, H = mag_heading(s, (roma.unitquat_to_rotmat(s.q)[0].T @ nm.mag_field)[None], nm.mag_field)
    np.testing.assert_allclose(H[0, 0, 6:9].numpy(), num, atol=1e-8)


def test_baro_and_receiver_std_gps_updates():
    s, rng = _random_state(6, B=2)
    h = torch.from_numpy(rng.standard_normal((2, 1)))
    a, ia = baro_update(s, h, MAG_NM)
    assert torch.equal(ia.r, h - s.p[:, 2:3])
    b, _ = update(s, h - s.p[:, 2:3], BARO_IDX, MAG_NM.baro_std)
    assert torch.equal(a.P, b.P) and torch.equal(a.p, b.p)
    # the receiver's own std per fix: the same as a noise model holding it
    pos, vel = (torch.from_numpy(rng.standard_normal((2, 3))) for _ in range(2))
    std = torch.tensor([[0.4, 0.4, 0.9, 0.2, 0.2, 0.3], [2.0, 2.0, 3.0, 0.5, 0.5, 0.6]], dtype=torch.float64)
    got, inn = gps_update(s, pos, vel, MAG_NM, std=std)
    for i in range(2):
        one = init_state(s.p[i:i + 1], s.v[i:i + 1], s.q[i:i + 1], s.ba[i:i + 1], s.bg[i:i + 1], s.P[i:i + 1])
        ref, ref_inn = gps_update(one, pos[i:i + 1], vel[i:i + 1], replace(MAG_NM, gps_std=std[i]))
        assert torch.allclose(got.P[i], ref.P[0], atol=1e-14) and torch.allclose(inn.nis[i], ref_inn.nis[0])
    scaled, _ = gps_update(s, pos, vel, MAG_NM, std=std, std_scale=torch.tensor([1.0, 2.0]))
    assert torch.equal(scaled.P[0], got.P[0]) and not torch.equal(scaled.P[1], got.P[1])


def test_masked_update_leaves_excluded_flights_untouched():
    s, rng = _random_state(1, B=3)
    r = torch.from_numpy(rng.standard_normal((3, 6)))
    new, inn = update(s, r, GPS_IDX, NM.gps_std, mask=torch.tensor([True, False, True]))
    assert torch.equal(new.p[1], s.p[1]) and torch.equal(new.P[1], s.P[1])
    assert not torch.equal(new.p[0], s.p[0])
    assert inn.nis.shape == (3,)


def _error(a, b):
    dth = roma.unitquat_to_rotvec(roma.quat_product(roma.quat_conjugation(b.q), a.q))
    return torch.cat([a.p - b.p, a.v - b.v, dth, a.ba - b.ba, a.bg - b.bg], -1)


def _perturb(s, dx):
    return init_state(s.p + dx[:, 0:3], s.v + dx[:, 3:6],
                      roma.quat_product(s.q, roma.rotvec_to_unitquat(dx[:, 6:9])),
                      s.ba + dx[:, 9:12], s.bg + dx[:, 12:15], s.P)


def test_predict_jacobian_matches_finite_differences():
    """F used for the covariance equals the numerical Jacobian of the nominal propagation."""
    rng = np.random.default_rng(2)
    q = roma.rotvec_to_unitquat(torch.from_numpy(rng.standard_normal((1, 3)) * 0.5))
    s = init_state(rng.standard_normal((1, 3)), rng.standard_normal((1, 3)), q,
                   0.1 * rng.standard_normal((1, 3)), 0.05 * rng.standard_normal((1, 3)),
                   np.eye(15)[None])
    acc = torch.tensor([[0.5, -0.3, 9.9]], dtype=torch.float64)
    gyro = torch.tensor([[0.4, -0.2, 0.3]], dtype=torch.float64)
    dt, eps = 0.01, 1e-6
    zero = NoiseModel(0.0, 0.0, 0.0, 0.0, NM.gps_std, NM.vio_std)
    base = predict(s, acc, gyro, dt, zero)
    F_num = np.zeros((15, 15))
    for i in range(15):
        dx = torch.zeros(1, 15, dtype=torch.float64)
        dx[0, i] = eps
        F_num[:, i] = (_error(predict(_perturb(s, dx), acc, gyro, dt, zero), base)[0] / eps).numpy()
    # P0 = I and Q = 0, so the propagated covariance is F F^T
    assert np.allclose(base.P[0].numpy(), F_num @ F_num.T, atol=1e-6)


def test_vehicle_tracks_mission_without_attack(consistency_run):
    """The controller flies on the estimate: without an attack every one of the 32 flights stays
    within 3 m of its mission (here, beside the other test of this shared run, so that it is
    simulated once)."""
    r = consistency_run
    dev = np.linalg.norm(r["true_pos"] - r["ref_pos"], axis=-1)
    assert dev.max() < 3.0


def test_nis_and_nees_consistent_with_gaussian_white_noise(consistency_run):
    """No Gauss-Markov error, no attack: mean NIS within 10% of 6; NEES within chi-square bounds."""
    r = consistency_run
    nis = r["res_gps_nis"][:, 20:, 0]       # after the first 2 s
    assert nis.mean() == pytest.approx(6.0, rel=0.10)
    nees = r["nees"][:, 20:]
    B = nees.shape[0]
    lo, hi = chi2.ppf([0.025, 0.975], 9 * B) / B     # 95% bounds of the flight-averaged NEES
    avg = nees.mean(0)
    assert ((avg > lo) & (avg < hi)).mean() >= 0.85
    assert nees.mean() == pytest.approx(9.0, rel=0.15)
    # whitened innovations have unit variance per axis
    assert np.allclose((r["res_gps_w"][:, 20:] ** 2).mean((0, 1)), 1.0, atol=0.15)


def test_default_noise_nis_within_30_percent(bias_dataset):
    f = bias_dataset.flights
    clean = f[(f.label == 0) & (f.t > 2.0)]
    assert clean.res_gps_nis.mean() == pytest.approx(6.0, rel=0.30)
    attacked = f[f.label == 1]
    assert attacked.res_gps_nis.mean() > 2 * clean.res_gps_nis.mean()


@pytest.fixture(scope="module", params=["gps+imu+mag+baro", "gps+imu+vio+mag+baro"])
def aided_consistency_run(request):
    """Gaussian white noise only (no GPS or barometer Gauss-Markov error, no magnetometer bias),
    no attack, 8 flights of 12 s."""
    cfg = SimConfig(model="I", noise="gaussian", flights=8, duration=12.0, seed=11, sensors=request.param,
                    gps=GPSConfig(gm_std=0.0), mag=MagConfig(bias_std=0.0), baro=BaroConfig(gm_std=0.0))
    return simulate_batch(cfg, np.arange(8), np.zeros(8, dtype=bool), record_nees=True)


def test_nis_and_nees_consistent_with_magnetometer_and_barometer(aided_consistency_run):
    """Mean NIS of every update inside its 99% chi-square bounds (the last update of each sensor
    before each GPS step, after the first 2 s); NEES as for the default configuration."""
    r = aided_consistency_run
    groups = [("res_gps_nis", 6), ("res_mag_nis", 1), ("res_baro_nis", 1)]
    groups += [("res_vio_nis", 6)] if "res_vio_nis" in r else []
    for group, dof in groups:
        nis = r[group][:, 20:, 0]
        lo, hi = chi2.ppf([0.005, 0.995], dof * nis.size) / nis.size
        assert lo < nis.mean() < hi, (group, nis.mean(), lo, hi)
    nees = r["nees"][:, 20:]
    B = nees.shape[0]
    lo, hi = chi2.ppf([0.025, 0.975], 9 * B) / B
    avg = nees.mean(0)
    assert ((avg > lo) & (avg < hi)).mean() >= 0.85
    assert nees.mean() == pytest.approx(9.0, rel=0.15)
