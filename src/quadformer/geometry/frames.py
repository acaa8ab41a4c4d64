"""Frame and unit conversions applied once, at the edge of every source (logs, live links).

Conventions (ROS REP-103): the world frame is ENU (x east, y north, z up), the body
frame is FLU (x forward, y left, z up), units are SI. PX4 and ArduPilot log and stream NED
(x north, y east, z down) and FRD (x forward, y right, z down):

    ENU <- NED:  (x, y, z)_enu = (y, x, -z)_ned     (a proper rotation, 180 deg about (1, 1, 0)/sqrt 2)
    FLU <- FRD:  (x, y, z)_flu = (x, -y, -z)_frd    (180 deg about x)

An attitude quaternion q_ned_frd (body FRD -> world NED) becomes
q_enu_flu = Q_ENU_NED * q_ned_frd * Q_FRD_FLU. Quaternions are Hamilton products in
(x, y, z, w) order here; PX4 and ArduPilot log (w, x, y, z), so readers call
``wxyz_to_xyzw`` first. Geodetic positions become local ENU through
``pymap3d.geodetic2enu`` about an origin (lat deg, lon deg, alt m). Altitudes are used as
logged (AMSL for PX4 and ArduPilot GPS, ellipsoidal for ROS NavSatFix); origin and
points of one log use the same altitude datum, so the local frame is consistent.

Every function is vectorised over leading axes and returns new arrays.
"""

from __future__ import annotations

import numpy as np
import pymap3d

__all__ = ["ENU_FROM_NED", "FLU_FROM_FRD", "Q_ENU_NED", "Q_FRD_FLU", "enu_to_geodetic", "euler_to_quat",
           "frd_to_flu", "geodetic_to_enu", "ned_to_enu", "ned_var_to_enu", "quat_multiply",
           "quat_ned_frd_to_enu_flu", "quat_normalize", "quat_rotate", "quat_to_euler", "quat_to_matrix",
           "wxyz_to_xyzw", "xyzw_to_wxyz"]

ENU_FROM_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
FLU_FROM_FRD = np.diag([1.0, -1.0, -1.0])
_S = np.sqrt(0.5)
Q_ENU_NED = np.array([_S, _S, 0.0, 0.0])   # xyzw: 180 deg about (1, 1, 0)/sqrt 2
Q_FRD_FLU = np.array([1.0, 0.0, 0.0, 0.0])  # xyzw: 180 deg about x


def ned_to_enu(v: np.ndarray) -> np.ndarray:
    """Vectors (..., 3) in NED -> ENU."""
    v = np.asarray(v, dtype=float)
    return np.stack([v[..., 1], v[..., 0], -v[..., 2]], axis=-1)


def ned_var_to_enu(var: np.ndarray) -> np.ndarray:
    """Per-axis variances (..., 3) in NED -> ENU (a permutation; signs do not apply)."""
    var = np.asarray(var, dtype=float)
    return np.stack([var[..., 1], var[..., 0], var[..., 2]], axis=-1)


def frd_to_flu(v: np.ndarray) -> np.ndarray:
    """Body vectors (..., 3) in FRD -> FLU."""
    v = np.asarray(v, dtype=float)
    return np.stack([v[..., 0], -v[..., 1], -v[..., 2]], axis=-1)


def wxyz_to_xyzw(q: np.ndarray) -> np.ndarray:
    """Reorder quaternions (..., 4) from (w, x, y, z) to (x, y, z, w)."""
    q = np.asarray(q, dtype=float)
    return np.concatenate([q[..., 1:4], q[..., 0:1]], axis=-1)


def xyzw_to_wxyz(q: np.ndarray) -> np.ndarray:
    """Reorder quaternions (..., 4) from (x, y, z, w) to (w, x, y, z) (MAVLink's order)."""
    q = np.asarray(q, dtype=float)
    return np.concatenate([q[..., 3:4], q[..., 0:3]], axis=-1)


def quat_normalize(q: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4); a zero or non-finite quaternion becomes NaN."""
    q = np.asarray(q, dtype=float)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        n = np.linalg.norm(q, axis=-1, keepdims=True)
        out = q / n
    return np.where(n > 0, out, np.nan)


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b of (x, y, z, w) quaternions, broadcast over leading axes."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    ax, ay, az, aw = (a[..., i] for i in range(4))
    bx, by, bz, bw = (b[..., i] for i in range(4))
    return np.stack([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz], axis=-1)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of unit (x, y, z, w) quaternions."""
    x, y, z, w = (np.asarray(q, dtype=float)[..., i] for i in range(4))
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
    ], axis=-2)


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors v (..., 3) by unit quaternions q (..., 4): R(q) v."""
    return np.einsum("...ij,...j->...i", quat_to_matrix(q), np.asarray(v, dtype=float))


def quat_ned_frd_to_enu_flu(q: np.ndarray) -> np.ndarray:
    """Attitude (x, y, z, w) body FRD -> world NED  ->  body FLU -> world ENU. Both frame
    changes are 180 deg rotations, so the same map takes ENU/FLU back to NED/FRD."""
    q = quat_multiply(quat_multiply(Q_ENU_NED, q), Q_FRD_FLU)
    # keep w >= 0 so that equal rotations compare equal
    return quat_normalize(np.where(q[..., 3:4] < 0, -q, q))


def euler_to_quat(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """(x, y, z, w) quaternion of Z-Y-X Euler angles (rad): R = Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr = np.cos(np.asarray(roll, float) / 2), np.sin(np.asarray(roll, float) / 2)
    cp, sp = np.cos(np.asarray(pitch, float) / 2), np.sin(np.asarray(pitch, float) / 2)
    cy, sy = np.cos(np.asarray(yaw, float) / 2), np.sin(np.asarray(yaw, float) / 2)
    return np.stack([sr * cp * cy - cr * sp * sy,
                     cr * sp * cy + sr * cp * sy,
                     cr * cp * sy - sr * sp * cy,
                     cr * cp * cy + sr * sp * sy], axis=-1)


def quat_to_euler(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Z-Y-X Euler angles (roll, pitch, yaw; rad) of unit (x, y, z, w) quaternions, the inverse
    of ``euler_to_quat`` (pitch in [-pi/2, pi/2], roll and yaw in [-pi, pi])."""
    q = np.asarray(q, dtype=float)
    x, y, z, w = (q[..., i] for i in range(4))
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


def geodetic_to_enu(lat: np.ndarray, lon: np.ndarray, alt: np.ndarray,
                    origin: tuple[float, float, float]) -> np.ndarray:
    """WGS84 latitude/longitude (deg) and altitude (m) -> ENU (..., 3) metres about origin."""
    lat, lon, alt = (np.asarray(a, dtype=float) for a in (lat, lon, alt))
    e, n, u = pymap3d.geodetic2enu(lat, lon, alt, float(origin[0]), float(origin[1]),
                                   float(origin[2]), deg=True)
    return np.stack(np.broadcast_arrays(e, n, u), axis=-1).astype(float)


def enu_to_geodetic(enu: np.ndarray, origin: tuple[float, float, float]) -> np.ndarray:
    """ENU (..., 3) metres about origin -> (..., 3) WGS84 latitude, longitude (deg), altitude (m);
    the inverse of ``geodetic_to_enu``."""
    enu = np.asarray(enu, dtype=float)
    lat, lon, alt = pymap3d.enu2geodetic(enu[..., 0], enu[..., 1], enu[..., 2], float(origin[0]),
                                         float(origin[1]), float(origin[2]), deg=True)
    return np.stack(np.broadcast_arrays(lat, lon, alt), axis=-1).astype(float)
