"""Part 2: missions, plant and the estimator in the loop."""

import numpy as np
import pytest
import torch

from quadformer.config import MissionConfig
from quadformer.missions import sample_missions
from quadformer.plant import Plant
from quadformer.rng import Stream, batch_generators


def test_mission_derivatives_and_ranges():
    cfg = MissionConfig()
    m = sample_missions(batch_generators(5, np.arange(24), Stream.SCENARIO), cfg, 60.0)
    assert set(m.kind) == {"hover", "circle", "lissajous", "minsnap"}
    t = np.arange(0.0, 60.0, 0.01)
    p, v, a = m.evaluate(t)
    # analytic derivatives agree with finite differences of the position
    assert np.abs(np.gradient(p, 0.01, axis=1)[:, 1:-1] - v[:, 1:-1]).max() < 1e-3
    assert np.abs(np.gradient(v, 0.01, axis=1)[:, 1:-1] - a[:, 1:-1]).max() < 1e-2
    speed = np.linalg.norm(v, axis=-1)
    moving = m.kind != "hover"
    # cruise speed within the sampled 1..8 m/s (figure-8 peaks at the cruise speed)
    assert np.all(speed[moving].max(1) <= 1.4 * m.speed[moving])   # min-snap peaks up to ~1.35x cruise
    assert np.all(speed[moving].mean(1) >= 0.5 * m.speed[moving])
    assert np.all((m.speed >= 1.0) & (m.speed <= 8.0))
    assert p[..., 2].min() >= 5.0 - 0.5 and p[..., 2].max() <= 30.0 + 3.0


@pytest.mark.parametrize("model", ["I", "II"])
def test_hover_equilibrium(model):
    """rotorpy's vehicle at hover rotor speeds with the controller on the true state stays put."""
    B = 2
    pos0 = np.tile([0.0, 0.0, 10.0], (B, 1))
    plant = Plant(model, pos0, np.zeros((B, 3)))
    zeros = torch.zeros(B, dtype=torch.float64)
    ref = {"x": torch.from_numpy(pos0), "x_dot": torch.zeros(B, 3, dtype=torch.float64),
           "x_ddot": torch.zeros(B, 3, dtype=torch.float64), "yaw": zeros, "yaw_dot": zeros}
    wind = torch.zeros(B, 3, dtype=torch.float64)
    for _ in range(200):
        state = plant.step(plant.control(plant.state, ref), wind, 0.01)
    assert np.abs(state["x"].numpy() - pos0).max() < 1e-3
    assert torch.allclose(state["q"].norm(dim=-1), torch.ones(B, dtype=torch.float64))


def test_spoof_moves_the_real_vehicle(bias_dataset):
    """The controller flies on the estimate: a bias pulls the true vehicle off its mission."""
    f = bias_dataset.flights
    s = bias_dataset.scenarios.set_index("flight_id")
    dev = np.linalg.norm(f[["true_pos_x", "true_pos_y", "true_pos_z"]].to_numpy()
                         - f[["ref_pos_x", "ref_pos_y", "ref_pos_z"]].to_numpy(), axis=1)
    f = f.assign(dev=dev)
    for fid, row in s[s.attacked].iterrows():
        g = f[f.flight_id == fid]
        during = g[(g.t >= row.onset + 4.0) & (g.label == 1)].dev
        before = g[g.t < row.onset].dev
        # VIO-aided, the filter yields to the spoof over seconds; the vehicle follows it
        assert during.max() > 0.3 * row.magnitude
        assert during.max() > before.max() + 0.5


def test_gps_correction_integral_remembers_an_absorbed_spoof(bias_dataset):
    """res_gps_corr_*: the filter absorbs a bias, the innovation fades, the integral of the
    corrections GPS applied keeps pointing along the spoof until it ends."""
    f = bias_dataset.flights
    s = bias_dataset.scenarios
    cols = ["res_gps_corr_px", "res_gps_corr_py", "res_gps_corr_pz"]
    clean_max = max(np.linalg.norm(f[f.flight_id == i][cols].to_numpy(), axis=1).max()
                    for i in s.flight_id[~s.attacked])
    for _, row in s[s.attacked].iterrows():
        g = f[(f.flight_id == row.flight_id) & (f.label == 1)]
        proj = g[cols].to_numpy() @ np.array([row.dir_x, row.dir_y, row.dir_z])
        assert proj[-1] > 1.0 and proj[-1] > clean_max
