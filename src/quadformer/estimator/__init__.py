"""Error-state EKF fusing IMU, GPS and VIO; its GPS innovations are the residues."""

from quadformer.estimator.eskf import (
    ERROR_STATES,
    EKFState,
    Innovation,
    NoiseModel,
    gps_update,
    init_state,
    predict,
    update,
    vio_update,
)

__all__ = ["ERROR_STATES", "EKFState", "Innovation", "NoiseModel", "gps_update", "init_state",
           "predict", "update", "vio_update"]
