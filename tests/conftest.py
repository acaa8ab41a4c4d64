"""Shared fixtures: small but real simulated datasets, simulated once per session."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from quadformer.config import AttackConfig, GPSConfig, SimConfig
from quadformer.simulation import simulate
from quadformer.simulation.closed_loop import simulate_batch

torch.set_num_threads(1)   # the simulator's small tensor operations run fastest on one thread


@pytest.fixture(scope="session")
def bias_dataset():
    """Model II in wind, laplace noise, bias attacks on half of 6 flights of 24 s."""
    cfg = SimConfig(model="II", noise="laplace", flights=6, duration=24.0, seed=3,
                    attack=AttackConfig(kind="bias", onset=(6.0, 10.0), duration=(6.0, 10.0)))
    return simulate(cfg)


@pytest.fixture(scope="session")
def consistency_run():
    """Gaussian white noise only, no attack: the filter's own assumptions hold. 32 flights of
    15 s in one batch: the simulator's cost grows with the flights' length, hardly with their
    number, and the statistics see about as many steps as in 16 flights of 30 s."""
    cfg = SimConfig(model="I", noise="gaussian", flights=32, duration=15.0, seed=11,
                    gps=GPSConfig(gm_std=0.0))
    return simulate_batch(cfg, np.arange(32), np.zeros(32, dtype=bool), record_nees=True)
