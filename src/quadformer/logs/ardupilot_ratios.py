"""ArduPilot's GPS innovation test ratios: what they are, the gates they are taken against, and
the innovation variances a reader recovers from them (ArduPilot logs innovations and test
ratios, but no innovation variances).

Definitions (ArduPilot's source; ``i`` an innovation, predicted minus measured, ``S = P + R``
the innovation variance of the consistency check, ``g`` the gate in standard deviations):

* EKF3, ``libraries/AP_NavEKF3/AP_NavEKF3_PosVelFusion.cpp`` (``FuseVelPosNED``):

  - velTestRatio = (i_N^2 + i_E^2 [+ i_D^2]) / ((S_N + S_E [+ S_D]) g_vel^2): one ratio summed
    over the fused velocity axes; the vertical one is left out (N, E only) where the vertical
    velocity is not fused: no vertical velocity source (``EK3_SRC1_VELZ`` not GPS; before 4.1
    ``EK3_GPS_TYPE`` 1 or more), a receiver without vertical velocity, or no absolute aiding;
  - posTestRatio = (i_N^2 + i_E^2) / ((S_N + S_E) g_pos^2);
  - hgtTestRatio = i_D^2 / (S_D g_hgt^2), of the active height source: the barometer by
    default (``EK3_SRC1_POSZ`` 1; 3 is GPS; before 4.1 ``EK3_ALT_SOURCE`` 0 baro, 2 GPS), so
    the logged vertical position innovation and its ratio are the GPS's only where the height
    source is GPS;
  - g = max(0.01 ``EK3_VEL_I_GATE`` / ``EK3_POS_I_GATE`` / ``EK3_HGT_I_GATE``, 1); the
    parameters' default is 500, 5 standard deviations (``AP_NavEKF3.cpp``);
  - S adds to the state variance the variance of the check (``R_OBS_DATA_CHECKS``): for the
    velocity the noise parameter scaled with manoeuvres (``EK3_VELNE_M_NSE``, not the
    receiver's speed accuracy), for position and height the measurement variance of the update.

* EKF2, ``libraries/AP_NavEKF2/AP_NavEKF2_PosVelFusion.cpp``: the same three ratios, the gates
  ``EK2_VEL_I_GATE``, ``EK2_POS_I_GATE``, ``EK2_HGT_I_GATE`` (default 500: 5 standard
  deviations, taken as max(0.01 value, 1)); the velocity sums N, E, D unless ``EK2_GPS_TYPE``
  is 1 or more (N, E); the height source is ``EK2_ALT_SOURCE`` (0 baro, the default; 2 GPS).

* ArduPilot's first EKF, ``libraries/AP_NavEKF/AP_NavEKF.cpp`` (2014-15, ArduPilot before
  3.4): velTestRatio and hgtTestRatio as above, with gates in standard deviations as they are
  (``EKF_VEL_GATE``, ``EKF_HGT_GATE``; copter and rover defaults 5 and 10, plane 6 and 20), the
  velocity over N, E, D unless ``EKF_GPS_TYPE`` is 1 (N, E), the height the barometer's. Its
  posTestRatio is not over the innovation variance but over an acceptance radius:
  (i_N^2 + i_E^2) / ((``EKF_POS_GATE`` ``EKF_POSNE_NOISE``)^2 + (0.005 (1 + 0.1 |a|)
  ``EKF_GLITCH_ACCEL`` dt^2)^2), dt the time since the last position passed (the real logs of
  that EKF agree: |i| / SP is 5.0 to 5.2 m there, ``EKF_POS_GATE`` 10 times
  ``EKF_POSNE_NOISE`` 0.5). Its position variance cannot be recovered.

What the logs hold (``AP_NavEKF3_Logging.cpp``, ``AP_NavEKF2_Logging.cpp``, and for the first
EKF the vehicle's DataFlash code, ``Log_Write_EKF``): ``XKF4``/``NKF4``/``EKF4`` fields ``SV``,
``SP``, ``SH`` are int16(100 sqrt(ratio)) (``getVariances`` returns the square roots of the
test ratios despite its name) in the format character ``c`` (int16 x 0.01), so a DataFlash
reader gets the square roots themselves: ratio = SV^2, SP^2, SH^2; every version does this.
``XKF3``/``NKF3``/``EKF3`` ``IVN..IPD`` are int16(100 i) in ``c``: the innovations in m, m/s.
The live link's ``EKF_STATUS_REPORT`` carries the same square roots (``send_status_report``).

Recovery. With a group's ratio r, gate g and innovations i of the axes it sums, its summed
innovation variance is S = sum(i^2) / (r g^2), and each axis is given the share S / n (n axes):
the ratio says nothing of how S divides among the axes, so an equal share is the one the data
allow. The group's normalised innovation squared over those shares, n sum(i^2) / S = n g^2 r,
depends on the ratio alone; only its direction comes from the innovations. A step whose ratio
is 0 or NaN, or whose innovations of the group are all 0 or not finite, holds no variance: its
group is left unfused (NaN variance, weight 0 in the residues), never divided by zero.
Approximations beside the equal share: the logged innovations are those of the sequential
update (each axis after the earlier axes' corrections), the ratio's those before it; the values
are quantised to 0.01 (m, m/s, and square roots of ratios), which dominates for small ratios.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = ["FAMILIES", "GATE_PARAMS", "RatioModel", "gate_sigma", "innovation_test_ratios", "ratio_model",
           "recover_variances"]

#: the estimator message families: EKF3 (XKF*), EKF2 (NKF*), ArduPilot's first EKF (EKF*)
FAMILIES = {"XKF": "EKF3", "NKF": "EKF2", "EKF": "ArduPilot's first EKF"}
#: the gate parameters (velocity, horizontal position, height) per family
GATE_PARAMS = {"XKF": ("EK3_VEL_I_GATE", "EK3_POS_I_GATE", "EK3_HGT_I_GATE"),
               "NKF": ("EK2_VEL_I_GATE", "EK2_POS_I_GATE", "EK2_HGT_I_GATE"),
               "EKF": ("EKF_VEL_GATE", "EKF_POS_GATE", "EKF_HGT_GATE")}
#: their defaults: EKF2 and EKF3 in hundredths of a standard deviation, the first EKF in standard
#: deviations by vehicle (AP_NavEKF.cpp: copter and rover, plane and others)
DEFAULT_GATES = {"XKF": (500.0, 500.0, 500.0), "NKF": (500.0, 500.0, 500.0),
                 "EKF": {"copter": (5.0, 10.0, 10.0), "rover": (5.0, 10.0, 10.0), "plane": (6.0, 30.0, 20.0)}}
GROUPS = ("vel", "pos", "hgt")
#: the FlightLog innovation columns (ENU) each group sums
AXES = {"pos": (0, 1), "hgt": (2,), "vel": (3, 4, 5)}
GPS_SOURCE = 3                       # EK3_SRC1_* value of GPS
GPS_ALT_SOURCE = 2                   # EK2_ALT_SOURCE / EK3_ALT_SOURCE value of GPS


def gate_sigma(name: str, value: float) -> float:
    """A gate parameter in standard deviations: the ``*_I_GATE`` parameters of EKF2 and EKF3 are
    hundredths, taken as max(0.01 value, 1); the first EKF's ``EKF_*_GATE`` are standard
    deviations as they are."""
    return max(0.01 * value, 1.0) if name.endswith("_I_GATE") else float(value)


@dataclass(frozen=True)
class RatioModel:
    """What one log's test ratios mean: the family, the gates (standard deviations: velocity,
    horizontal position, height), the velocity axes the velocity ratio sums (2: N, E; 3: N, E,
    D; 0: GPS velocity not fused), whether the position ratio is over the innovation variance
    (False: the first EKF's acceptance radius, or GPS position not fused) and whether the height
    ratio is the GPS's (its height source is GPS); notes: how each was found."""
    family: str
    gates: tuple[float, float, float]
    vel_axes: int = 3
    pos_variance: bool = True
    hgt_gps: bool = False
    notes: tuple[str, ...] = field(default_factory=tuple)

    def axes(self) -> dict[str, tuple[int, ...]]:
        """The FlightLog innovation columns each recoverable group sums (a group left out: none)."""
        return {"vel": AXES["vel"][:self.vel_axes], "pos": AXES["pos"] if self.pos_variance else (),
                "hgt": AXES["hgt"] if self.hgt_gps else ()}


def _vehicle_kind(firmware: str | None) -> str:
    text = (firmware or "").lower()
    if "plane" in text:
        return "plane"
    if "rover" in text:
        return "rover"
    return "copter"


def _number(params: dict, name: str) -> float | None:
    v = params.get(name)
    return float(v) if isinstance(v, (int, float)) and math.isfinite(v) else None


def ratio_model(family: str, params: dict, firmware: str | None = None,
                receiver_vz: bool = True) -> RatioModel:
    """The meaning of a log's test ratios from its estimator family (``FAMILIES``), its
    parameters (PARM, name -> value at the log's start), its firmware text (the first EKF's
    defaults differ by vehicle) and whether its receiver gives a vertical velocity (GPA.VV)."""
    if family not in FAMILIES:
        raise ValueError(f"unknown ArduPilot estimator family {family!r}; expected one of {', '.join(FAMILIES)}")
    notes = []
    defaults = DEFAULT_GATES[family]
    if isinstance(defaults, dict):
        kind = _vehicle_kind(firmware)
        defaults = defaults[kind]
    gates, said = [], []
    for name, default in zip(GATE_PARAMS[family], defaults):
        value = _number(params, name)
        if value is not None and value <= 0:
            notes.append(f"{name} {value:g} is not a gate; its default {default:g} used")
            value = None
        sigma = gate_sigma(name, default if value is None else value)
        said.append(f"{name} {default if value is None else value:g}" + (" (default)" if value is None else "")
                    + f" -> {sigma:g} sigma")
        gates.append(sigma)
    notes.append("gates " + ", ".join(said))
    # the axes and sources of GPS fusion
    if family == "XKF":
        velz, velxy, posxy, posz = (_number(params, f"EK3_SRC1_{k}") for k in ("VELZ", "VELXY", "POSXY", "POSZ"))
        gps_type, alt = _number(params, "EK3_GPS_TYPE"), _number(params, "EK3_ALT_SOURCE")
        if velxy is not None or posxy is not None or velz is not None or posz is not None:
            vel_on = velxy is None or velxy == GPS_SOURCE
            vz_on = velz is None or velz == GPS_SOURCE
            pos_on = posxy is None or posxy == GPS_SOURCE
            hgt_gps = posz is not None and posz == GPS_SOURCE
            how = "EK3_SRC1_VELXY/VELZ/POSXY/POSZ"
        else:
            vel_on = gps_type is None or gps_type < 2
            pos_on = gps_type is None or gps_type < 3
            vz_on = gps_type is None or gps_type == 0
            hgt_gps = alt is not None and alt == GPS_ALT_SOURCE
            how = "EK3_GPS_TYPE/EK3_ALT_SOURCE" if gps_type is not None or alt is not None else "defaults"
    else:
        prefix = "EK2" if family == "NKF" else "EKF"
        gps_type = _number(params, f"{prefix}_GPS_TYPE")
        vel_on = gps_type is None or gps_type < 2
        vz_on = gps_type is None or gps_type == 0
        pos_on = gps_type is None or gps_type < 3
        alt = _number(params, "EK2_ALT_SOURCE") if family == "NKF" else None
        hgt_gps = alt is not None and alt == GPS_ALT_SOURCE
        how = f"{prefix}_GPS_TYPE" + ("/EK2_ALT_SOURCE" if family == "NKF" else "") \
            if gps_type is not None or alt is not None else "defaults"
    if family == "XKF" and vz_on and not receiver_vz:
        vz_on = False
        notes.append("the receiver gives no vertical velocity (GPA.VV 0): the velocity ratio sums N, E")
    vel_axes = 0 if not vel_on else (3 if vz_on else 2)
    notes.append("velocity ratio over " + {0: "no GPS velocity (not fused)", 2: "N, E", 3: "N, E, D"}[vel_axes]
                 + f" ({how})")
    pos_variance = pos_on and family != "EKF"
    if family == "EKF" and pos_on:
        notes.append("position ratio over the first EKF's acceptance radius (EKF_POS_GATE x EKF_POSNE_NOISE), "
                     "not a variance: horizontal position left unwhitened")
    elif not pos_on:
        notes.append(f"GPS position not fused ({how}): horizontal position left unwhitened")
    notes.append("height ratio " + ("of GPS (the height source)" if hgt_gps else
                                    "of the height source, not GPS (the barometer by default): vertical position "
                                    "left unwhitened"))
    return RatioModel(family, tuple(gates), vel_axes, pos_variance, hgt_gps, tuple(notes))


def innovation_test_ratios(innov: np.ndarray, var: np.ndarray, gates: tuple[float, float, float],
                vel_axes: np.ndarray | int = 3) -> dict[str, np.ndarray]:
    """ArduPilot's velocity, position and height test ratios (``ratio_vel``, ``ratio_pos``,
    ``ratio_hgt``) of innovations and their variances, (n, 6) each in the FlightLog's order
    (position x, y, z, velocity x, y, z; a sum over axes is the same in ENU and NED).
    ``vel_axes``: 2 or 3 per row (or for all), the velocity axes summed."""
    innov, var = np.asarray(innov, dtype=float), np.asarray(var, dtype=float)
    n3 = np.broadcast_to(np.asarray(vel_axes), (len(innov),)) == 3
    out = {}
    for g, gate in zip(GROUPS, gates):
        cols = list(AXES[g])
        num = (innov[:, cols] ** 2).sum(axis=1)
        den = var[:, cols].sum(axis=1)
        if g == "vel":                               # the vertical velocity only where it is summed
            num = np.where(n3, num, (innov[:, cols[:2]] ** 2).sum(axis=1))
            den = np.where(n3, den, var[:, cols[:2]].sum(axis=1))
        with np.errstate(divide="ignore", invalid="ignore"):
            out[f"ratio_{g}"] = num / (den * gate ** 2)
    return out


def recover_variances(innov: np.ndarray, ratios: dict[str, np.ndarray],
                      model: RatioModel) -> tuple[np.ndarray, dict[str, int]]:
    """The innovation variances (n, 6; the FlightLog's order) recovered from the test ratios
    (``ratio_vel``, ``ratio_pos``, ``ratio_hgt``, each (n,)) and the innovations: per group, the
    summed variance sum(i^2) / (r g^2) shared equally among its axes. NaN where a group holds no
    information at that step (a ratio of 0 or NaN, innovations all 0 or not finite) or is not
    recoverable (``RatioModel.axes``). Also the steps without information, per group."""
    innov = np.asarray(innov, dtype=float)
    var = np.full(innov.shape, np.nan)
    empty: dict[str, int] = {}
    for g, gate in zip(GROUPS, model.gates):
        cols = list(model.axes()[g])
        if not cols:
            continue
        r = np.asarray(ratios[f"ratio_{g}"], dtype=float)
        ss = (innov[:, cols] ** 2).sum(axis=1)
        ok = np.isfinite(r) & (r > 0) & np.isfinite(ss) & (ss > 0)
        share = np.full(len(r), np.nan)
        share[ok] = ss[ok] / (r[ok] * gate ** 2) / len(cols)
        var[:, cols] = share[:, None]
        empty[g] = int((~ok).sum())
    return var, empty
