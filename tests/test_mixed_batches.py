"""Flights of several configurations in one batch: each configuration's data is exactly
what it gets simulated alone; the dataset cache writes the same datasets."""

import json

import numpy as np
import pandas as pd
import pytest

from quadformer.config import AttackConfig, SimConfig
from quadformer.dataset import load_dataset
from quadformer.experiments.cache import dataset_key, ensure_configs
from quadformer.simulation import mixable, simulate, simulate_groups, simulate_many
from quadformer.simulation.closed_loop import simulate_batch
from quadformer.simulation.simulate import plan_batches

A = SimConfig(model="I", noise="exponential", flights=3, duration=3.0, seed=7,
              attack=AttackConfig(kind="bias", onset=(1.0, 2.0), fraction=0.7))
B = SimConfig(model="II", noise="laplace", flights=2, duration=3.0, seed=8,
              attack=AttackConfig(kind="ramp", onset=(1.0, 2.0), fraction=1.0))
C = SimConfig(model="II", noise="gaussian", flights=2, duration=3.0, seed=9,
              attack=AttackConfig(kind="mix", onset=(1.0, 2.0), fraction=1.0))


def _same(a, b):
    pd.testing.assert_frame_equal(a.flights, b.flights, check_exact=True)
    pd.testing.assert_frame_equal(a.scenarios, b.scenarios, check_exact=True)
    assert json.loads(json.dumps(a.meta)) == json.loads(json.dumps(b.meta))   # as written


@pytest.fixture(scope="module")
def alone():
    return [simulate(c) for c in (A, B, C)]


def test_mixed_batch_equals_each_config_alone(alone):
    together = simulate_many([A, B, C])
    for a, b in zip(together, alone):
        _same(a, b)
    # a batch of flights picked from each configuration: the same rows, bit for bit
    ids = [np.array([2, 0]), np.array([1]), np.array([0, 1])]
    rs = simulate_groups([(c, i, np.ones(len(i), bool)) for c, i in zip((A, B, C), ids)])
    for c, i, r in zip((A, B, C), ids, rs):
        solo = simulate_batch(c, i, np.ones(len(i), bool))
        for k in ("true_pos", "est_pos", "gps_pos", "res_gps_nis", "label", "atk_d", "ref_pos"):
            assert np.array_equal(r[k], solo[k]), k
        assert list(r["attacks"].kind) == list(solo["attacks"].kind)


def test_plan_batches_splits_flights_and_keeps_unmixable_apart():
    other = A.replace(dt=0.005)
    assert mixable(A, B) and not mixable(A, other)
    plan = plan_batches([A, B, other], n_batches=2)
    flat = sorted((i, int(f)) for batch in plan for i, ids in batch for f in ids)
    assert flat == [(0, 0), (0, 1), (0, 2), (1, 0), (1, 1), (2, 0), (2, 1), (2, 2)]
    assert all(len({i == 2 for i, _ in batch}) == 1 for batch in plan)   # config 2 never mixed
    assert len(plan_batches([A, B], n_batches=1)) == 1


def test_cache_writes_each_dataset_as_before(alone, tmp_path):
    paths = ensure_configs([("a", A), ("b", B), ("c", C)], tmp_path, progress=False, workers=2)
    for (name, cfg), ds in zip((("a", A), ("b", B), ("c", C)), alone):
        assert paths[name] == tmp_path / f"{name}-{dataset_key(cfg)}"
        _same(load_dataset(paths[name]), ds)
    assert ensure_configs([("a", A)], tmp_path, progress=False) == {"a": paths["a"]}   # cached: nothing to do
