"""Batch-invariant SO(3) maps agree with roma's reference implementation; the plane angle
agrees with numpy's."""

import numpy as np
import pytest
import roma
import torch

from quadformer.geometry import atan2, exp_quat, exp_rotmat, log_quat, wrap_angle


def test_maps_match_roma_small_and_large_angles():
    g = torch.Generator().manual_seed(0)
    for scale in (1e-6, 1e-3, 0.04, 0.5, 2.5):
        phi = torch.randn(200, 3, generator=g, dtype=torch.float64) * scale
        q = exp_quat(phi)
        assert torch.allclose(q, roma.rotvec_to_unitquat(phi), atol=1e-15, rtol=0)
        assert torch.allclose(log_quat(q), roma.unitquat_to_rotvec(q), atol=1e-14, rtol=0)
        assert torch.allclose(exp_rotmat(phi), roma.rotvec_to_rotmat(phi), atol=1e-12, rtol=0)
        if scale < 1.0:  # angles below pi: the log recovers phi from either quaternion sign
            assert torch.allclose(log_quat(-q), phi, atol=1e-12)


def test_results_do_not_depend_on_batch_position():
    g = torch.Generator().manual_seed(1)
    phi = torch.randn(67, 3, generator=g, dtype=torch.float64) * 0.02
    full_q, full_r = exp_quat(phi), log_quat(exp_quat(phi))
    for i in range(phi.shape[0]):
        assert torch.equal(exp_quat(phi[i:i + 1]), full_q[i:i + 1])
        assert torch.equal(log_quat(full_q[i:i + 1]), full_r[i:i + 1])
    assert np.isfinite(full_r.numpy()).all()


def test_atan2_matches_numpy_in_every_quadrant_and_at_every_scale():
    rng = np.random.default_rng(2)
    xy = rng.standard_normal((2, 20000)) * np.exp(rng.uniform(-15, 15, (1, 20000)))
    edges = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0], [-1.0, 1e-17], [-1.0, -1e-17],
                      [1.0, 1e-12], [1.0, -3e-9], [0.0, 0.0], [-2.0, 2.0]]).T
    x, y = np.concatenate([xy[0], edges[0]]), np.concatenate([xy[1], edges[1]])
    got = atan2(torch.from_numpy(y), torch.from_numpy(x)).numpy()
    ref = np.arctan2(y, x)
    np.testing.assert_allclose(got, ref, rtol=4e-15, atol=4e-15)
    # tiny angles keep their relative precision
    tiny = torch.tensor([1e-12, -3e-300], dtype=torch.float64)
    assert atan2(tiny, torch.ones(2, dtype=torch.float64)).tolist() == pytest.approx([1e-12, -3e-300], rel=1e-15)


def test_atan2_does_not_depend_on_batch_position_and_wraps_to_half_open_interval():
    g = torch.Generator().manual_seed(3)
    xy = torch.randn(2, 67, generator=g, dtype=torch.float64)
    full = atan2(xy[1], xy[0])
    for i in range(xy.shape[1]):
        assert torch.equal(atan2(xy[1, i:i + 1], xy[0, i:i + 1]), full[i:i + 1])
    w = wrap_angle(torch.tensor([np.pi, -np.pi, 0.5, np.pi - 1e-15], dtype=torch.float64))
    assert w.tolist() == [-np.pi, -np.pi, 0.5, np.pi - 1e-15]
