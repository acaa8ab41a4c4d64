"""Plant: rotorpy's ``BatchedMultirotor`` (rotor, drag and motor models, rk4) with wind.

Model I is rotorpy's ``hummingbird_params`` in calm air (mean wind under 1 m/s, light
gusts); Model II is rotorpy's ``px4_sihsim_quadx_params`` in Dryden turbulence with a mean
wind up to 6 m/s and a gust strength sampled per flight. Dryden gusts use rotorpy's
``BatchedGustModel`` filter; its driving noise comes from our per-flight generators
instead of torch's global one, so flights do not depend on their batch.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
from rotorpy.controllers.quadrotor_control import BatchedSE3Control
from rotorpy.vehicles.hummingbird_params import quad_params as hummingbird_params
from rotorpy.vehicles.multirotor import BatchedMultirotor, BatchedMultirotorParams
from rotorpy.vehicles.px4_sihsim_quadx_params import quad_params as px4_sihsim_quadx_params
from rotorpy.wind.dryden_utils import BatchedGustModel

VEHICLE_PARAMS = {"I": hummingbird_params, "II": px4_sihsim_quadx_params}

# Wind per model: mean speed range (m/s, horizontal, random direction) and gust std range (m/s).
WIND = {"I": {"mean": (0.0, 0.8), "gust": (0.0, 0.1)},
        "II": {"mean": (0.0, 6.0), "gust": (0.3, 1.5)}}

# Tracking errors handed to the SE(3) controller are bounded, as an autopilot's position
# controller bounds its setpoints; otherwise a jump of the estimate (a spoof, a reset)
# asks for accelerations that saturate the motors and flip the vehicle.
MAX_POS_ERR = 1.0   # m, per axis
MAX_VEL_ERR = 2.0   # m/s, per axis

# SE(3) controller attitude gains for the PX4 SIH quad (its slower motors, tau 0.05 s, need
# softer gains than rotorpy's defaults, which suit the hummingbird).
ATTITUDE_GAINS = {"I": None, "II": (150.0, 25.0)}


@dataclass(frozen=True)
class WindBatch:
    mean: np.ndarray      # (B, 3) m/s
    gust_std: np.ndarray  # (B, 3) m/s, Dryden turbulence intensity per axis


def sample_wind(gens: list[np.random.Generator], model: str) -> WindBatch:
    lo, hi = WIND[model]["mean"]
    glo, ghi = WIND[model]["gust"]
    mean = np.zeros((len(gens), 3))
    gust = np.zeros((len(gens), 3))
    for b, rng in enumerate(gens):
        speed, heading = rng.uniform(lo, hi), rng.uniform(0, 2 * np.pi)
        mean[b, :2] = speed * np.cos(heading), speed * np.sin(heading)
        g = rng.uniform(glo, ghi)
        gust[b] = (g, g, 0.5 * g)
    return WindBatch(mean, gust)


class _DrawnGust(BatchedGustModel):
    """rotorpy's Dryden gust filter with the uniform driving noise supplied by the caller."""

    def step(self, dt: float, u_k: torch.Tensor) -> torch.Tensor:
        c1 = 1.0 + 2 * self.delta / dt + 4 * self.gamma / dt**2
        c2 = 2.0 - 8 * self.gamma / dt**2
        c3 = 1.0 - 2 * self.delta / dt + 4 * self.gamma / dt**2
        c4 = self.alpha + 2 * self.beta / dt
        c5 = 2 * self.alpha
        c6 = self.alpha - 2 * self.beta / dt
        y_k = (c4 * u_k + c5 * self.u_km1 + c6 * self.u_km2 - c2 * self.y_km1 - c3 * self.y_km2) / c1
        self.u_km2, self.u_km1 = self.u_km1, u_k
        self.y_km2, self.y_km1 = self.y_km1, y_k
        return y_k


class DrydenWind:
    """Batched Dryden wind (rotorpy's length scales and filters) with external draws."""

    def __init__(self, wind: WindBatch, altitude: np.ndarray):
        B = wind.mean.shape[0]
        alt = torch.as_tensor(altitude, dtype=torch.float64)
        lz_ft = 3.281 * alt
        lx_ft = lz_ft / ((0.177 + 0.000823 * lz_ft) ** 1.2)
        sig = torch.as_tensor(wind.gust_std, dtype=torch.float64)
        self.mean = torch.as_tensor(wind.mean, dtype=torch.float64)
        self.axes = [
            _dryden_axis(lx_ft / 3.281, sig[:, 0], B),
            _dryden_axis(lx_ft / 3.281, sig[:, 1], B),
            _dryden_axis(lz_ft / 3.281, sig[:, 2], B),
        ]

    def update(self, dt: float, uniforms: torch.Tensor) -> torch.Tensor:
        """uniforms: (B, 3) draws in [-1, 1]. Returns the wind (B, 3) in m/s."""
        g = torch.stack([ax.step(dt, uniforms[:, i]) for i, ax in enumerate(self.axes)], dim=-1)
        return self.mean + g


def _dryden_axis(length: torch.Tensor, sigma: torch.Tensor, batch: int) -> _DrawnGust:
    gust = _DrawnGust(1.0, length, sigma, batch_size=batch, device="cpu")
    gust.u_km1 = gust.u_km1.double()
    gust.u_km2 = gust.u_km2.double()
    gust.y_km1 = gust.y_km1.double()
    gust.y_km2 = gust.y_km2.double()
    return gust


def concat_wind(parts: list[WindBatch]) -> WindBatch:
    """The flights of several ``WindBatch`` in one, in order."""
    return WindBatch(np.concatenate([w.mean for w in parts]), np.concatenate([w.gust_std for w in parts]))


class Plant:
    """A batch of vehicles, rotorpy dynamics plus its SE(3) controller.

    model: the vehicle model of every flight (``"I"``, ``"II"``) or of each flight (a
    sequence of B names): rotorpy takes per-vehicle parameters, so flights of both models
    fly in one batch, each exactly as in a batch of its own model."""

    def __init__(self, model: str | Sequence[str], pos0: np.ndarray, vel0: np.ndarray):
        B = pos0.shape[0]
        models = [model] * B if isinstance(model, str) else [str(m) for m in model]
        assert len(models) == B
        self.model = model
        self.device = torch.device("cpu")
        self.params = BatchedMultirotorParams([VEHICLE_PARAMS[m] for m in models], B, self.device)
        # rotorpy draws motor-speed noise from torch's global RNG; both models have none.
        assert float(self.params.motor_noise.abs().max()) == 0.0
        self.idx = torch.arange(B)
        hover = torch.tensor([float(np.sqrt(p["mass"] * 9.81 / (p["num_rotors"] * p["k_eta"])))
                              for p in (VEHICLE_PARAMS[m] for m in models)], dtype=torch.float64)
        self.state = {
            "x": torch.as_tensor(pos0, dtype=torch.float64).clone(),
            "v": torch.as_tensor(vel0, dtype=torch.float64).clone(),
            "q": torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64).repeat(B, 1),
            "w": torch.zeros(B, 3, dtype=torch.float64),
            "wind": torch.zeros(B, 3, dtype=torch.float64),
            "rotor_speeds": hover[:, None].repeat(1, 4),
        }
        self.vehicle = BatchedMultirotor(self.params, B, self.state, self.device,
                                         control_abstraction="cmd_motor_speeds", aero=True, integrator="rk4")
        kw = {}
        if any(ATTITUDE_GAINS[m] is not None for m in models):
            # rotorpy's gains (per vehicle) where the model keeps them, ours where it sets its own
            kp = self.params.kp_att.double().reshape(B, -1)[:, :1].clone()
            kd = self.params.kd_att.double().reshape(B, -1)[:, :1].clone()
            for b, m in enumerate(models):
                if ATTITUDE_GAINS[m] is not None:
                    kp[b], kd[b] = ATTITUDE_GAINS[m]
            kw = {"kp_att": kp, "kd_att": kd}
        self.controller = BatchedSE3Control(self.params, B, self.device, **kw)

    def control(self, est: dict[str, torch.Tensor], ref: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Motor commands that track ``ref`` from the estimated state ``est``."""
        bounded = dict(ref)
        bounded["x"] = est["x"] + (ref["x"] - est["x"]).clamp(-MAX_POS_ERR, MAX_POS_ERR)
        bounded["x_dot"] = est["v"] + (ref["x_dot"] - est["v"]).clamp(-MAX_VEL_ERR, MAX_VEL_ERR)
        return self.controller.update(0.0, est, bounded, idxs=self.idx)

    def step(self, control: dict[str, torch.Tensor], wind: torch.Tensor, dt: float) -> dict[str, torch.Tensor]:
        self.state["wind"] = wind
        self.state = self.vehicle.step(self.state, control, dt, idxs=self.idx)
        return self.state
