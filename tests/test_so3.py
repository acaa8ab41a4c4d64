"""Batch-invariant SO(3) maps agree with roma's reference implementation."""

import numpy as np
import roma
import torch

from quadformer.geometry import exp_quat, exp_rotmat, log_quat


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
