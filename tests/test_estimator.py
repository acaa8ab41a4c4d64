"""Part 5: the error-state EKF: reference equivalence, Jacobians, consistency."""

import numpy as np
import pytest
import roma
import torch
from filterpy.kalman import ExtendedKalmanFilter
from scipy.stats import chi2

from quadformer.estimator.eskf import GPS_IDX, NoiseModel, init_state, predict, update

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
