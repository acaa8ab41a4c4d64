"""Geometry shared by the vehicle, the sensors and the estimator: SO(3) maps for unit
quaternions, plane angles and batched products whose per-flight result does not depend on
the batch."""

from quadformer.geometry.angles import atan2, wrap_angle
from quadformer.geometry.linalg import bmm, matvec
from quadformer.geometry.so3 import exp_quat, exp_rotmat, log_quat

__all__ = ["atan2", "bmm", "exp_quat", "exp_rotmat", "log_quat", "matvec", "wrap_angle"]
