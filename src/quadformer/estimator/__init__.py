"""Error-state EKF fusing IMU, GPS and, as configured, VIO, magnetometer and barometer; its
innovations are the residues."""

from quadformer.estimator.eskf import (
    ERROR_STATES,
    EKFState,
    Innovation,
    NoiseModel,
    baro_update,
    gps_update,
    init_state,
    mag_update,
    predict,
    update,
    vio_update,
)

__all__ = ["ERROR_STATES", "EKFState", "Innovation", "NoiseModel", "baro_update", "gps_update", "init_state",
           "mag_update", "predict", "update", "vio_update"]
