"""Error-state extended Kalman filter, batched over flights (torch, float64).

Nominal state: position p, velocity v (world, ENU, m and m/s), attitude q (unit
quaternion, xyzw, body to world), accelerometer bias ba and gyro bias bg. Error state
(15): dp, dv, dtheta (local angle error, q_true = q * Exp(dtheta)), dba, dbg.

Pure functions: ``predict`` and ``update`` return new states. GPS (position, velocity),
VIO (velocity, attitude) and the barometer (height) observe a subset of the error state
directly (H is a selection), which ``update`` exploits; the magnetometer heading has a
general H. S is factorised by Cholesky and never inverted.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import roma
import torch

from quadformer.estimator.noise import simulated_noise
from quadformer.geometry import atan2, bmm, exp_quat, exp_rotmat, log_quat, matvec, wrap_angle

ERROR_STATES = ("px", "py", "pz", "vx", "vy", "vz", "thx", "thy", "thz",
                "bax", "bay", "baz", "bgx", "bgy", "bgz")
GRAVITY = torch.tensor([0.0, 0.0, -9.81], dtype=torch.float64)
GPS_IDX = torch.arange(0, 6)
VIO_IDX = torch.arange(3, 9)
BARO_IDX = torch.arange(2, 3)


@dataclass(frozen=True)
class EKFState:
    p: torch.Tensor    # (B,3)
    v: torch.Tensor    # (B,3)
    q: torch.Tensor    # (B,4) xyzw
    ba: torch.Tensor   # (B,3)
    bg: torch.Tensor   # (B,3)
    P: torch.Tensor    # (B,15,15)


@dataclass(frozen=True)
class NoiseModel:
    """Per-step process noise and measurement noise standard deviations, and the Earth
    magnetic field the magnetometer heading is measured against."""
    accel_std: float      # m/s^2 per IMU sample
    gyro_std: float       # rad/s per IMU sample
    accel_walk: float     # m/s^2 per IMU sample (bias random walk)
    gyro_walk: float      # rad/s per IMU sample
    gps_std: torch.Tensor  # (6,) position m, velocity m/s
    vio_std: torch.Tensor  # (6,) velocity m/s, attitude rad
    mag_std: torch.Tensor | None = None    # (1,) heading, rad
    baro_std: torch.Tensor | None = None   # (1,) height, m
    mag_field: torch.Tensor | None = None  # (3,) Earth field, world frame (ENU), gauss


@dataclass(frozen=True)
class Innovation:
    r: torch.Tensor      # (B,m) raw innovation z - h(x)
    w: torch.Tensor      # (B,m) whitened L^-1 r with S = L L^T
    nis: torch.Tensor    # (B,) r^T S^-1 r
    s_std: torch.Tensor  # (B,m) sqrt(diag S)
    dx: torch.Tensor | None = None   # (B,15) correction applied (zero where masked out)


def init_state(p, v, q, ba, bg, P0) -> EKFState:
    t = lambda x: torch.as_tensor(x, dtype=torch.float64).clone()  # noqa: E731
    return EKFState(t(p), t(v), t(q), t(ba), t(bg), t(P0))


def _skew(x: torch.Tensor) -> torch.Tensor:
    z = torch.zeros_like(x[:, 0])
    return torch.stack([torch.stack([z, -x[:, 2], x[:, 1]], -1),
                        torch.stack([x[:, 2], z, -x[:, 0]], -1),
                        torch.stack([-x[:, 1], x[:, 0], z], -1)], -2)


def predict(s: EKFState, accel: torch.Tensor, gyro: torch.Tensor, dt: float, nm: NoiseModel) -> EKFState:
    """Propagate with one IMU sample (specific force, body rate) over dt seconds."""
    B = s.p.shape[0]
    R = roma.unitquat_to_rotmat(s.q)
    f = accel - s.ba
    w = gyro - s.bg
    a = matvec(R, f) + GRAVITY
    p = s.p + s.v * dt + 0.5 * a * dt * dt
    v = s.v + a * dt
    q = roma.quat_normalize(roma.quat_product(s.q, exp_quat(w * dt)))

    eye3 = torch.eye(3, dtype=torch.float64).expand(B, 3, 3)
    F = torch.eye(15, dtype=torch.float64).repeat(B, 1, 1)
    Rf = -bmm(R, _skew(f))
    F[:, 0:3, 3:6] = eye3 * dt
    F[:, 0:3, 6:9] = Rf * (0.5 * dt * dt)      # from p += v dt + a dt^2 / 2
    F[:, 0:3, 9:12] = -R * (0.5 * dt * dt)
    F[:, 3:6, 6:9] = Rf * dt
    F[:, 3:6, 9:12] = -R * dt
    F[:, 6:9, 6:9] = exp_rotmat(-w * dt)
    F[:, 6:9, 12:15] = -(eye3 - 0.5 * _skew(w * dt)) * dt   # right Jacobian of Exp, first order
    P = bmm(bmm(F, s.P), F.transpose(1, 2))
    q_diag = torch.tensor([(nm.accel_std * dt) ** 2] * 3 + [(nm.gyro_std * dt) ** 2] * 3
                          + [nm.accel_walk ** 2] * 3 + [nm.gyro_walk ** 2] * 3, dtype=torch.float64)
    d = torch.arange(3, 15)
    P[:, d, d] += q_diag
    return EKFState(p, v, q, s.ba, s.bg, P)


def update(s: EKFState, r: torch.Tensor, h: torch.Tensor, std: torch.Tensor,
           mask: torch.Tensor | None = None) -> tuple[EKFState, Innovation]:
    """Kalman update with innovation ``r`` (B,m) = H dx + noise.

    h: an integer index tensor (m,) of the error states the measurement observes directly
    (H a selection, the cheaper path), or H itself, floating point (B,m,15) or (m,15).
    std: (m,) measurement noise std, or (B,m) per flight (an inflated noise while a sensor is
    re-admitted). ``mask`` (B,) selects the flights whose state is corrected; the innovation
    statistics are computed for all flights.
    """
    B, m = r.shape
    std = std.to(torch.float64)
    Rm = torch.diag_embed(std**2) if std.dim() == 2 else torch.diag(std**2)
    general = h.is_floating_point()
    if general:
        H = h.to(torch.float64).expand(B, m, 15)
        PHt = bmm(s.P, H.transpose(1, 2))                  # (B,15,m)
        S = bmm(H, PHt) + Rm                               # (B,m,m)
    else:
        PHt = s.P[:, :, h]                                 # (B,15,m)
        S = PHt[:, h, :] + Rm                              # (B,m,m)
    S = 0.5 * (S + S.transpose(1, 2))
    L = torch.linalg.cholesky(S)
    wht = torch.linalg.solve_triangular(L, r.unsqueeze(-1), upper=False).squeeze(-1)
    innov = Innovation(r, wht, (wht * wht).sum(-1), torch.sqrt(torch.diagonal(S, dim1=1, dim2=2)))

    Kt = torch.cholesky_solve(PHt.transpose(1, 2), L)      # (B,m,15) = S^-1 H P
    K = Kt.transpose(1, 2)                                 # (B,15,m)
    dx = matvec(K, r)                                      # (B,15)
    A = torch.eye(15, dtype=torch.float64).repeat(B, 1, 1)
    if general:
        A = A - bmm(K, H)
    else:
        A[:, :, h] -= K
    var = (std**2).unsqueeze(1) if std.dim() == 2 else std**2
    P = bmm(bmm(A, s.P), A.transpose(1, 2)) + bmm(K * var, Kt)   # Joseph form
    P = 0.5 * (P + P.transpose(1, 2))

    p = s.p + dx[:, 0:3]
    v = s.v + dx[:, 3:6]
    q = roma.quat_normalize(roma.quat_product(s.q, exp_quat(dx[:, 6:9])))
    ba = s.ba + dx[:, 9:12]
    bg = s.bg + dx[:, 12:15]
    new = EKFState(p, v, q, ba, bg, P)
    if mask is not None:
        new = _select(mask, new, s)
        dx = torch.where(mask.view(-1, 1), dx, torch.zeros_like(dx))
    return new, replace(innov, dx=dx)


def _select(mask: torch.Tensor, a: EKFState, b: EKFState) -> EKFState:
    m1 = mask.view(-1, 1)
    return EKFState(torch.where(m1, a.p, b.p), torch.where(m1, a.v, b.v), torch.where(m1, a.q, b.q),
                    torch.where(m1, a.ba, b.ba), torch.where(m1, a.bg, b.bg),
                    torch.where(mask.view(-1, 1, 1), a.P, b.P))


def gps_update(s: EKFState, pos: torch.Tensor, vel: torch.Tensor, nm: NoiseModel, mask=None,
               std_scale: torch.Tensor | None = None, std: torch.Tensor | None = None):
    """GPS position and velocity update. ``std`` (B,6): the receiver's own accuracy per flight
    (position m, velocity m/s) in place of ``nm.gps_std``; ``std_scale`` (B,) multiplies the
    measurement noise std per flight."""
    r = torch.cat([pos - s.p, vel - s.v], dim=-1)
    base = nm.gps_std if std is None else std.to(torch.float64)
    std = base if std_scale is None else std_scale.to(torch.float64)[:, None] * base
    return update(s, r, GPS_IDX, std, mask)


def reset_to_gps(s: EKFState, pos: torch.Tensor, vel: torch.Tensor, nm: NoiseModel,
                 mask: torch.Tensor) -> EKFState:
    """Reset position and velocity of the flights in ``mask`` to a GPS fix (what PX4 EKF2 does
    after GPS has been rejected for too long): states set to the fix, their covariance to the
    GPS noise, their cross-covariances cleared."""
    P = s.P.clone()
    P[:, 0:6, :] = 0.0
    P[:, :, 0:6] = 0.0
    P[:, GPS_IDX, GPS_IDX] = nm.gps_std.to(torch.float64) ** 2
    new = EKFState(pos.to(torch.float64), vel.to(torch.float64), s.q, s.ba, s.bg, P)
    return _select(mask, new, s)


def vio_update(s: EKFState, vel: torch.Tensor, q_meas: torch.Tensor, nm: NoiseModel, mask=None):
    dtheta = log_quat(roma.quat_product(roma.quat_conjugation(s.q), q_meas))
    r = torch.cat([vel - s.v, dtheta], dim=-1)
    return update(s, r, VIO_IDX, nm.vio_std, mask)


def baro_update(s: EKFState, height: torch.Tensor, nm: NoiseModel, mask=None):
    """Barometric height update: ``height`` (B,1), m, in the world frame (ENU z)."""
    return update(s, height - s.p[:, 2:3], BARO_IDX, nm.baro_std, mask)


def mag_heading(s: EKFState, mag: torch.Tensor, field: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Heading innovation (B,1) of the body-frame magnetic field ``mag`` (B,3) against the
    Earth field ``field`` (3,) (world, ENU), and its H (B,1,15).

    The field rotated to the world frame with the estimated attitude, m = R mag, is compared
    with f = ``field`` in the horizontal plane: the innovation is the angle from m_h to f_h,
    wrapped to [-pi, pi), which is the measured heading (the field tilt-compensated with the
    estimated roll and pitch) minus the estimated heading. To first order it is H dtheta with
    H = R[2,:] - f_z / |f_h|^2 (f_x R[0,:] + f_y R[1,:]): the third row of R (the heading
    error), plus the heading error that a roll or pitch error puts into the tilt compensation
    through the vertical field.
    """
    R = roma.unitquat_to_rotmat(s.q)
    m = matvec(R, mag)
    fx, fy, fz = (float(v) for v in field)
    cross = m[:, 0] * fy - m[:, 1] * fx
    dot = m[:, 0] * fx + m[:, 1] * fy
    r = wrap_angle(atan2(cross, dot)).unsqueeze(-1)
    H = torch.zeros(len(r), 1, 15, dtype=torch.float64)
    H[:, 0, 6:9] = R[:, 2, :] - fz / (fx * fx + fy * fy) * (fx * R[:, 0, :] + fy * R[:, 1, :])
    return r, H


def mag_update(s: EKFState, mag: torch.Tensor, nm: NoiseModel, mask=None):
    """Magnetometer heading update from the body-frame field ``mag`` (B,3), gauss, against
    ``nm.mag_field`` (see ``mag_heading``)."""
    r, H = mag_heading(s, mag, nm.mag_field)
    return update(s, r, H, nm.mag_std, mask)


def state_error(s: EKFState, p, v, q) -> torch.Tensor:
    """True minus estimated (dp, dv, dtheta): (B,9), for NEES."""
    dth = log_quat(roma.quat_product(roma.quat_conjugation(s.q), q))
    return torch.cat([p - s.p, v - s.v, dth], dim=-1)


def nees(s: EKFState, p, v, q) -> torch.Tensor:
    """Normalised estimation error squared over position, velocity and attitude (9 dof)."""
    e = state_error(s, p, v, q)
    L = torch.linalg.cholesky(s.P[:, :9, :9])
    z = torch.linalg.solve_triangular(L, e.unsqueeze(-1), upper=False).squeeze(-1)
    return (z * z).sum(-1)


def noise_model(imu_cfg, gps_cfg, vio_cfg, ekf_cfg, imu_rate_hz: float, mag_cfg=None, baro_cfg=None
                ) -> NoiseModel:
    """Filter noise matched to the sensor configuration unless ``ekf_cfg`` overrides it
    (``mag_cfg`` and ``baro_cfg``: default ``MagConfig()`` and ``BaroConfig()``):
    ``noise.simulated_noise`` as torch tensors."""
    n = simulated_noise(imu_cfg, gps_cfg, vio_cfg, ekf_cfg, imu_rate_hz, mag_cfg, baro_cfg)
    return NoiseModel(accel_std=n.accel_std, gyro_std=n.gyro_std, accel_walk=n.accel_walk, gyro_walk=n.gyro_walk,
                      gps_std=torch.from_numpy(n.gps_std), vio_std=torch.from_numpy(n.vio_std),
                      mag_std=torch.from_numpy(n.mag_std), baro_std=torch.from_numpy(n.baro_std),
                      mag_field=torch.from_numpy(n.mag_field))

