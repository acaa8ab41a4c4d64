"""Batched sensor models. All noise is drawn from per-flight generators in blocks.

IMU: rotorpy's error model (white noise of std ``density * sqrt(rate / 2)`` per sample,
bias random walk of std ``walk / sqrt(rate / 2)`` per sample), on the specific force and
body rates of the plant.
GPS: local ENU position and velocity, white noise of the chosen shape plus a first-order
Gauss-Markov position error.
VIO: world-frame velocity, attitude, and position in its own odometry frame whose drift
grows with the distance travelled.
Magnetometer: the Earth field in the body frame (FLU), ``R^T m_world``, plus a hard-iron bias
(constant per flight, optionally walking) and white noise of the chosen shape.
Barometer: the world-frame height ``p_z`` plus a first-order Gauss-Markov bias and white
noise of the chosen shape.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import roma
import torch

from quadformer.config import BaroConfig, GPSConfig, IMUConfig, MagConfig, VIOConfig
from quadformer.geometry import exp_quat, matvec
from quadformer.sensors.noise import batch_noise

GRAVITY = torch.tensor([0.0, 0.0, -9.81], dtype=torch.float64)


class ChunkedNoise:
    """Standard noise of one shape (or ``"uniform"`` on [-1, 1]), ``dims`` values per call,
    drawn per flight in blocks.

    Each flight's generator is only ever asked for blocks of ``block`` calls, so its draws
    do not depend on how many flights are simulated together. ``shape`` may also name each
    flight's own shape (a sequence of B names: flights of several configurations in one batch).
    """

    def __init__(self, gens: list[np.random.Generator], shape: str | Sequence[str], dims: int, block: int = 100):
        self.gens, self.dims, self.block = gens, dims, block
        self.shape = shape if isinstance(shape, str) or len(set(shape)) > 1 else str(shape[0])
        self._buf = torch.empty(0)
        self._i = block

    def _fill(self) -> np.ndarray:
        if not isinstance(self.shape, str):    # per-flight shapes: each flight draws exactly as alone
            out = np.empty((len(self.gens), self.block, self.dims))
            for b, (g, s) in enumerate(zip(self.gens, self.shape)):
                out[b] = self._draw([g], s)[0]
            return out
        return self._draw(self.gens, self.shape)

    def _draw(self, gens: list[np.random.Generator], shape: str) -> np.ndarray:
        if shape == "uniform":
            return np.stack([g.uniform(-1.0, 1.0, (self.block, self.dims)) for g in gens])
        return batch_noise(gens, shape, (self.block, self.dims))

    def next(self) -> torch.Tensor:
        if self._i >= self.block:
            self._buf = torch.from_numpy(self._fill())
            self._i = 0
        out = self._buf[:, self._i]
        self._i += 1
        return out


class IMU:
    def __init__(self, cfg: IMUConfig, rate_hz: float, gens: list[np.random.Generator],
                 accel_bias0: np.ndarray, gyro_bias0: np.ndarray):
        self.scale = float(np.sqrt(rate_hz / 2.0))
        self.accel_std = cfg.accel_noise_density * self.scale      # per sample
        self.gyro_std = cfg.gyro_noise_density * self.scale
        self.accel_walk = cfg.accel_bias_walk / self.scale         # per sample
        self.gyro_walk = cfg.gyro_bias_walk / self.scale
        self.accel_bias = torch.as_tensor(accel_bias0, dtype=torch.float64).clone()
        self.gyro_bias = torch.as_tensor(gyro_bias0, dtype=torch.float64).clone()
        self.noise = ChunkedNoise(gens, "gaussian", 12)

    def measure(self, acc_world: torch.Tensor, rates_body: torch.Tensor, rot: torch.Tensor):
        """Specific force (B,3) and angular rate (B,3) in the body frame."""
        n = self.noise.next()
        self.accel_bias = self.accel_bias + self.accel_walk * n[:, 0:3]
        self.gyro_bias = self.gyro_bias + self.gyro_walk * n[:, 3:6]
        f = matvec(rot.transpose(-1, -2), acc_world - GRAVITY)
        accel = f + self.accel_bias + self.accel_std * n[:, 6:9]
        gyro = rates_body + self.gyro_bias + self.gyro_std * n[:, 9:12]
        return accel, gyro


class GPS:
    def __init__(self, cfg: GPSConfig, shape: str, gens: list[np.random.Generator]):
        self.cfg = cfg
        self.pos_std = torch.tensor([cfg.pos_std_h, cfg.pos_std_h, cfg.pos_std_v], dtype=torch.float64)
        self.phi = float(np.exp(-1.0 / (cfg.rate_hz * cfg.gm_tau)))
        self.white = ChunkedNoise(gens, shape, 6, block=50)
        self.drive = ChunkedNoise(gens, "gaussian", 3, block=50)
        self.gm = None

    def measure(self, pos: torch.Tensor, vel: torch.Tensor):
        """Honest GPS fix (position, velocity) before any attack."""
        n = self.drive.next()
        if self.gm is None:
            self.gm = self.cfg.gm_std * n
        else:
            self.gm = self.phi * self.gm + self.cfg.gm_std * np.sqrt(1.0 - self.phi**2) * n
        w = self.white.next()
        return pos + self.gm + self.pos_std * w[:, 0:3], vel + self.cfg.vel_std * w[:, 3:6]


class VIO:
    def __init__(self, cfg: VIOConfig, shape: str, gens: list[np.random.Generator], pos0: torch.Tensor):
        self.cfg = cfg
        self.att_std = float(np.deg2rad(cfg.att_std_deg))
        self.noise = ChunkedNoise(gens, shape, 6, block=50)
        self.drift_noise = ChunkedNoise(gens, "gaussian", 3, block=50)
        self.origin = pos0.clone()
        self.last_pos = pos0.clone()
        self.drift = torch.zeros_like(pos0)
        self.direction = None

    def measure(self, pos: torch.Tensor, vel: torch.Tensor, q: torch.Tensor):
        """VIO velocity (world), attitude quaternion (xyzw) and odometry-frame position."""
        n = self.noise.next()
        d = self.drift_noise.next()
        # drift: 1% of the distance travelled along a slowly wandering direction
        self.direction = d if self.direction is None else self.direction + 0.05 * d
        unit = self.direction / self.direction.norm(dim=-1, keepdim=True).clamp_min(1e-9)
        travelled = (pos - self.last_pos).norm(dim=-1, keepdim=True)
        self.drift = self.drift + self.cfg.drift_fraction * travelled * unit
        self.last_pos = pos.clone()
        vel_m = vel + self.cfg.vel_std * n[:, 0:3]
        q_m = roma.quat_product(q, exp_quat(self.att_std * n[:, 3:6]))
        return vel_m, q_m, pos - self.origin + self.drift


class Magnetometer:
    def __init__(self, cfg: MagConfig, shape: str, gens: list[np.random.Generator]):
        self.cfg = cfg
        self.field = torch.tensor(cfg.field_enu, dtype=torch.float64)
        self.bias = torch.from_numpy(np.stack([g.standard_normal(3) for g in gens]) * cfg.bias_std)
        self.walk_std = cfg.bias_walk * float(np.sqrt(1.0 / cfg.rate_hz))   # gauss per sample
        self.white = ChunkedNoise(gens, shape, 3, block=50)
        self.drive = ChunkedNoise(gens, "gaussian", 3, block=50)

    def measure(self, rot: torch.Tensor) -> torch.Tensor:
        """Body-frame field (B,3), gauss, for body-to-world rotations ``rot`` (B,3,3)."""
        self.bias = self.bias + self.walk_std * self.drive.next()
        field = matvec(rot.transpose(-1, -2), self.field.expand(rot.shape[0], 3))
        return field + self.bias + self.cfg.noise_std * self.white.next()


class Barometer:
    def __init__(self, cfg: BaroConfig, shape: str, gens: list[np.random.Generator]):
        self.cfg = cfg
        self.phi = float(np.exp(-1.0 / (cfg.rate_hz * cfg.gm_tau)))
        self.white = ChunkedNoise(gens, shape, 1, block=50)
        self.drive = ChunkedNoise(gens, "gaussian", 1, block=50)
        self.gm = None

    def measure(self, pos: torch.Tensor) -> torch.Tensor:
        """Height (B,1), m, in the world frame, for positions ``pos`` (B,3)."""
        n = self.drive.next()
        if self.gm is None:
            self.gm = self.cfg.gm_std * n
        else:
            self.gm = self.phi * self.gm + self.cfg.gm_std * np.sqrt(1.0 - self.phi**2) * n
        return pos[:, 2:3] + self.gm + self.cfg.noise_std * self.white.next()
