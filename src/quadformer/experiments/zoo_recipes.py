"""The shipped detectors' recipes (``RECIPES``): per sensor set, the simulated flights its
detectors learn from (configurations, flights per configuration), the methods, and how its
default is chosen; with the numbers they rest on (the fleet's sensor noise, the paper profile's
figures the cards cite, glr's floor from real clean flights). ``experiments.zoo`` builds them."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from quadformer.config import SimConfig, merge
from quadformer.experiments.grid import PAPER_GRID, Profile, profile_configs

__all__ = ["FLEET_GLR_THRESHOLD", "FLEET_NOISE", "PAPER_PROFILE_F1", "RECIPES", "Recipe", "fleet_grid",
           "paper_grid"]

#: sensor noise of a fleet of real ArduCopter vehicles: what ``logs.noise.estimate_noise``
#: measured on the six clean flights of the field benchmark's set the filter replays (those of
#: ``docs/results/field-shipped/results.json``), the IMU and the receiver as the filter meets them
#: over a GPS interval (``logs.noise.interval_noise``, 4187 intervals in the air): the IMU pooled,
#: the receivers' white velocity noise the largest of the six (0.10 m/s, an Erle-Copter's), their
#: white position noise below the simulator's floor (0.05 m). Before, the fixes against the
#: autopilot's estimate (0.35 m/s, 0.16 m: that estimate's jitter) and the IMU's raw samples of
#: three of these flights (0.74 m/s^2/sqrt(Hz)) made the simulated vehicle three to five times
#: noisier than the real ones on the evidence a consistent drift leaves (one interval's velocity
#: step against the IMU: 0.5 m/s, where the real ones show 0.04 to 0.3). Only these numbers are
#: used, no log is shipped.
FLEET_NOISE: dict[str, Any] = {
    "gps": {"gm_std": 0.7435303125050816, "pos_std_h": 0.05, "pos_std_v": 0.9220703536609853,
            "vel_std": 0.10414412725051712},
    "imu": {"accel_noise_density": 0.40981569843935706, "gyro_noise_density": 0.023251744335514874},
    "mag": {"noise_std": 0.0018132049135960002},
    "baro": {"gm_std": 4.231174405439167, "noise_std": 0.47591915466248536},
}


#: the paper profile's test F1 by method and configuration (docs/results.md, "Paper profile":
#: `quadformer benchmark --profile paper`, commit 47559b9: a model per configuration, 360 training
#: flights each), which the ``vio`` set's cards and the demo cite beside their own figures
PAPER_PROFILE_F1: dict[str, dict[str, float]] = {
    m: dict(zip(("modelI-exponential-bias", "modelI-exponential-ramp", "modelI-laplace-bias", "modelI-laplace-ramp",
                 "modelII-exponential-bias", "modelII-exponential-ramp", "modelII-laplace-bias",
                 "modelII-laplace-ramp"), f1))
    for m, f1 in {
        "chi2": (0.51, 0.75, 0.56, 0.74, 0.51, 0.75, 0.55, 0.76),
        "cusum": (0.54, 0.75, 0.53, 0.69, 0.58, 0.68, 0.54, 0.71),
        "sprt": (0.58, 0.77, 0.65, 0.77, 0.62, 0.75, 0.67, 0.77),
        "bht": (0.63, 0.79, 0.70, 0.77, 0.67, 0.77, 0.70, 0.79),
        "chi2-vref": (0.19, 0.78, 0.19, 0.72, 0.21, 0.72, 0.20, 0.73),
        "cusum-vref": (0.20, 0.76, 0.18, 0.69, 0.20, 0.68, 0.19, 0.71),
        "cusum-ref": (0.50, 0.75, 0.50, 0.67, 0.52, 0.67, 0.51, 0.70),
        "quadformer": (0.91, 0.98, 0.90, 0.98, 0.92, 0.99, 0.93, 0.99),
    }.items()}


def paper_grid(flights: int, seed: int, duration: float = 60.0) -> list[tuple[str, SimConfig]]:
    """The paper's eight configurations (GPS + IMU + VIO; Model I/II, exponential/Laplace noise,
    bias/ramp) at ``flights`` each, their seeds derived from ``seed``."""
    return profile_configs(Profile("zoo", flights, duration=duration, seed=seed, grid=PAPER_GRID))


def fleet_grid(flights: int, seed: int, duration: float = 60.0) -> list[tuple[str, SimConfig]]:
    """GPS + IMU + magnetometer + barometer with the fleet's noise, both airframes, half of the
    flights under a bias of 1 to 10 m or a ramp of 0.05 to 2 m/s (the field benchmark's ranges)."""
    out = []
    for i, model in enumerate(("I", "II")):
        cfg = SimConfig.from_dict(merge(FLEET_NOISE, {
            "model": model, "noise": "gaussian", "sensors": "gps+imu+mag+baro", "flights": flights,
            "duration": duration, "seed": int(np.random.SeedSequence(seed, spawn_key=(0x200, i)).generate_state(1)[0]),
            "attack": {"kind": "mix", "mix": ["bias", "ramp"], "magnitude": [1.0, 10.0], "rate": [0.05, 2.0],
                       "onset": [duration / 6, duration * 2 / 3]}}))
        out.append((f"fleet-model{model}-gaussian-mix", cfg))
    return out


@dataclass(frozen=True)
class Recipe:
    set: str                        # the set's name (file names start with it)
    sensors: str
    residues: str                   # "ekf" or "autopilot"
    formats: tuple[str, ...]        # log formats it serves (empty: any)
    methods: tuple[str, ...]        # in order of preference where the validation flights tie
    flights: int                    # per configuration
    configs: Callable[..., list[tuple[str, SimConfig]]]     # (flights, seed, duration) -> named configs
    about: str
    #: the set's default by design (None: chosen on the validation flights), and why
    default: str | None = None
    default_reason: str = ""
    #: a floor under the default's false-alarm-budget threshold from real clean flights (None: none),
    #: and where it comes from
    field_threshold: float | None = None
    field_source: str = ""


#: why a self-normalising test is the default of the sets real vehicles without a camera use
_GLR_DEFAULT = ("glr is the one method that normalises itself to each vehicle in the air (the spread of its own "
                "innovations, within 10 times the trained one) and reads the raw innovation, which a receiver's "
                "inflated accuracy cannot normalise away; simulated validation flights, all of one simulated "
                "noise, cannot show how a method meets a real vehicle's")
#: a floor under the shipped glr's budget threshold: the largest glr score of a spoofing alert in the
#: air on the real clean flights of the field benchmark's set was 51.5 (``quadformer detect`` over
#: that set with the shipped magbaro-glr at a threshold of 15: 18.6 to 51.5 on the four clean flights
#: the filter replays with spoofing alerts in the air; a score, not a log, is kept), rounded up to 60
FLEET_GLR_THRESHOLD = 60.0
_FLEET_GLR_SOURCE = ("the largest glr score of a spoofing alert in the air on the field benchmark's clean real "
                     "flights (51.5, joeydouglas_2014-10-18_20-44-05.bin), rounded up to 60")

RECIPES: tuple[Recipe, ...] = (
    Recipe("magbaro", "gps+imu+mag+baro", "ekf", (), ("glr", "quadformer", "cusum", "chi2", "cusum-ref",
                                                      "cusum-vref"),
           200, fleet_grid,
           "a vehicle without a camera (most PX4 and ArduPilot logs, a MAVLink link): the project's filter over "
           "GPS, IMU, magnetometer and barometer, trained with a real fleet's sensor noise",
           default="glr", default_reason=_GLR_DEFAULT, field_threshold=FLEET_GLR_THRESHOLD,
           field_source=_FLEET_GLR_SOURCE),
    Recipe("vio", "gps+imu+vio", "ekf", (), ("quadformer", "chi2", "cusum", "sprt", "bht", "chi2-vref", "cusum-vref",
                                               "cusum-ref"),
           60, paper_grid,
           "the paper's vehicle: GPS, IMU and stereo visual-inertial odometry, trained on the paper's eight "
           "configurations (both airframes, exponential and Laplace noise, bias and ramp attacks)"),
    Recipe("px4", "gps+imu+mag+baro", "autopilot", ("px4",), ("cusum", "chi2"), 200, fleet_grid,
           "PX4 logs scored on the autopilot's own GPS innovations (--residues autopilot): the NIS tests, "
           "trained on the simulated filter's NIS with the fleet's noise; PX4's NIS has its own scale, so "
           "calibrate on the vehicle's clean flights (quadformer calibrate) before trusting its false-alarm rate"),
    Recipe("ardupilot", "gps+imu+mag+baro", "autopilot", ("ardupilot",), ("glr", "cusum", "chi2"), 200, fleet_grid,
           "ArduPilot logs scored on the autopilot's own GPS innovations (--residues autopilot; EKF3's XKF3, EKF2's "
           "NKF3 or the first EKF's EKF3, variances recovered from the logged test ratios): trained on the "
           "simulated in-loop filter's innovations with the fleet's noise; glr normalises itself to the vehicle, "
           "the NIS tests need a calibration on its clean flights (quadformer calibrate)",
           default="glr", default_reason=_GLR_DEFAULT, field_threshold=FLEET_GLR_THRESHOLD,
           field_source=_FLEET_GLR_SOURCE + " (on the project's replay; the autopilot's innovations were not "
                        "measured for it)"),
)
