"""Shared fixtures: small but real simulated datasets, simulated once per session."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from quadformer.config import AttackConfig, GPSConfig, SimConfig
from quadformer.simulation import simulate
from quadformer.simulation.closed_loop import simulate_batch

torch.set_num_threads(1)   # the simulator's small tensor operations run fastest on one thread


@pytest.fixture(scope="session", autouse=True)
def _torch_stays_on_one_thread():
    """Keep torch on one thread for the whole session. The CLI and the local pool's in-process
    runs set torch's threads to the machine's cores (``io.set_threads``): with the suite's one
    test process per core, two threads per process oversubscribe the cores and the simulator's
    small operations run several times slower (70 s instead of 15 s for the resilience CLI
    test on a busy 2-core machine), in that test and in every later test of the process."""
    mp = pytest.MonkeyPatch()
    one = torch.set_num_threads
    mp.setattr(torch, "set_num_threads", lambda n: one(1))
    yield
    mp.undo()


@pytest.fixture(scope="session")
def bias_dataset():
    """Model II in wind, laplace noise, bias attacks on half of 6 flights of 24 s."""
    cfg = SimConfig(model="II", noise="laplace", flights=6, duration=24.0, seed=3,
                    attack=AttackConfig(kind="bias", onset=(6.0, 10.0), duration=(6.0, 10.0)))
    return simulate(cfg)


@pytest.fixture(scope="session")
def short_dataset():
    """Like the bias dataset (6 flights, half of them attacked) in flights of 10 s with bias
    attacks of 2.5-4 s from 2.5-4 s: for the runs that fly the test flights again under the
    resilience policies or score many copies of the dataset, whose time goes with the flights'
    length."""
    cfg = SimConfig(model="II", noise="laplace", flights=6, duration=10.0, seed=3,
                    attack=AttackConfig(kind="bias", onset=(2.5, 4.0), duration=(2.5, 4.0)))
    return simulate(cfg)


@pytest.fixture(scope="session")
def consistency_run():
    """Gaussian white noise only, no attack: the filter's own assumptions hold. 32 flights of
    15 s in one batch: the simulator's cost grows with the flights' length, hardly with their
    number, and the statistics see about as many steps as in 16 flights of 30 s."""
    cfg = SimConfig(model="I", noise="gaussian", flights=32, duration=15.0, seed=11,
                    gps=GPSConfig(gm_std=0.0))
    return simulate_batch(cfg, np.arange(32), np.zeros(32, dtype=bool), record_nees=True)
