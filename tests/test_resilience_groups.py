"""Closed-loop flights of several configurations in one batch, each driven by its own
detector: every configuration's results equal flying it alone."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from quadformer.config import AttackConfig, SimConfig
from quadformer.detectors import StreamGroup, make
from quadformer.detectors.attack_types import SHAPE_TYPES
from quadformer.experiments.resilience import batches_of, run_config, run_configs
from quadformer.simulation import simulate_many


@pytest.fixture(scope="module")
def two_configs():
    """Two configurations that differ in vehicle, noise and attack: 10 flights of 10 s each."""
    a = SimConfig(model="I", noise="exponential", flights=10, duration=10.0, seed=21,
                  attack=AttackConfig(kind="bias", onset=(2.0, 3.0), duration=(3.0, 4.0)))
    b = SimConfig(model="II", noise="laplace", flights=10, duration=10.0, seed=22,
                  attack=AttackConfig(kind="ramp", onset=(2.0, 3.0), duration=(3.0, 4.0)))
    return tuple(simulate_many([a, b]))          # flown in one batch; each equals simulate() alone


def test_configurations_flown_together_equal_each_flown_alone(two_configs):
    together = run_configs([(ds, None) for ds in two_configs], "cusum")
    for ds, (res, traj, alerts) in zip(two_configs, together):
        res1, traj1, alerts1 = run_config(ds, "cusum")
        pd.testing.assert_frame_equal(traj, traj1)          # bit for bit: same flights, same decisions
        pd.testing.assert_frame_equal(alerts, alerts1)
        assert res["policies"] == res1["policies"]
        assert res["threshold"] == res1["threshold"]
        # the resilient policy did act: some fixes excluded on attacked flights
        resilient = traj[traj.policy == "resilient"]
        assert (~resilient.fused[resilient.label == 1]).any()
        # its alerts typed by shape when raised and confirmed 5 s later
        assert len(alerts) and set(alerts.attack_type) | set(alerts.confirmed_type) <= set(SHAPE_TYPES)


def test_a_stream_group_gives_each_slice_its_own_detector(two_configs):
    dets = []
    for ds in two_configs:      # one CUSUM tuned on each configuration: different statistics
        f = ds.flights
        det = make("cusum").fit(f, f.label.to_numpy())
        dets.append(det.calibrate(float(np.quantile(det.decision_function(f), 0.9))))
    group = StreamGroup([dets[0].stream(2), dets[1].stream(3)])
    alone = [dets[0].stream(2), dets[1].stream(3)]
    feats = dets[0].features_
    assert list(dets[1].features_) == list(feats)
    probe = np.full((1, len(feats)), 100.0)   # far above nominal: both statistics rise, by different amounts
    assert dets[0].stream(1).update(probe).score != dets[1].stream(1).update(probe).score
    # real residues: two flights of the first configuration, three of the second, attacked ones among them
    pick = [(0, i) for i in two_configs[0].scenarios.flight_id[:2]] + \
        [(1, i) for i in two_configs[1].scenarios.flight_id[2:5]]
    assert any(two_configs[c].scenarios.set_index("flight_id").attacked[i] for c, i in pick)
    rows = np.stack([two_configs[c].flights.loc[lambda f: f.flight_id == i, feats].to_numpy() for c, i in pick], 1)
    alarms = 0
    for x in rows:
        step = group.update(x)
        a, b = alone[0].update(x[:2]), alone[1].update(x[2:])
        np.testing.assert_array_equal(step.score, np.concatenate([a.score, b.score]))
        np.testing.assert_array_equal(step.alarm, np.concatenate([a.alarm, b.alarm]))
        alarms += int(step.alarm.sum())
    assert 0 < alarms < rows.shape[0] * rows.shape[1]
    rng = np.random.default_rng(0)
    cols = {c: rng.chisquare(6, size=5) for c in feats}
    step = group.update(cols)
    assert step.score.shape == (5,)
    with pytest.raises(ValueError, match="residues must be 2 row"):
        group.update(rng.normal(size=(5, len(feats) + 1)))
    with pytest.raises(ValueError, match="at least one stream"):
        StreamGroup([])


def test_batches_deal_mixable_configurations_and_keep_others_apart():
    cfgs = [SimConfig(model=m, noise=n, flights=4) for m in ("I", "II") for n in ("exponential", "laplace")]
    assert batches_of(cfgs, 2) == [[0, 1], [2, 3]]
    assert batches_of(cfgs, 1) == [[0, 1, 2, 3]]
    assert batches_of(cfgs, 8) == [[0], [1], [2], [3]]
    other = SimConfig(model="I", flights=4, duration=30.0)   # a different duration: its own batch
    assert batches_of(cfgs + [other], 2) == [[0, 1], [2, 3], [4]]
