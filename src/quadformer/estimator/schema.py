"""The flight table's columns: names, groups and units, in one place.

Every source of flights (the simulator, a flight log, a live link) produces rows of this
table, one per GPS step; every detector reads its ``res_*`` residue columns. A group of
columns shares a prefix and a unit; its columns are ``{group}_{axis}`` (or the group name
alone for a scalar). Frames: world ENU, body FLU, SI units.

The columns follow the sensor configuration: the groups of an aiding sensor (VIO,
magnetometer, barometer) are present only when it is configured (``groups_for``).
"""

from __future__ import annotations

from dataclasses import dataclass

from quadformer.config import SHAPE_KINDS, parse_sensors

XYZ = ("x", "y", "z")
GPS_AXES = ("px", "py", "pz", "vx", "vy", "vz")      # GPS innovation: position then velocity
VIO_AXES = ("vx", "vy", "vz", "thx", "thy", "thz")   # VIO innovation: velocity then attitude

#: s, time constants of the leaky integrals of GPS position corrections (``res_gps_corr`` and the
#: further groups)
CORR_TAU = 20.0
CORR_TAUS = {"res_gps_corr5": 5.0, "res_gps_corr120": 120.0}

#: the attack shapes alerts are typed as (the shape typer's and QUADFormer's classes); a flight's
#: ``attack_type`` column holds "none" or its attack kind (``config.ATTACK_KINDS``: these, or a
#: drift or capture, which show as a ramp)
ATTACK_TYPES = SHAPE_KINDS


@dataclass(frozen=True)
class Group:
    name: str
    axes: tuple[str, ...]    # () for a scalar column
    unit: str
    meaning: str

    @property
    def columns(self) -> list[str]:
        return [f"{self.name}_{a}" for a in self.axes] if self.axes else [self.name]

    @property
    def width(self) -> int:
        return max(1, len(self.axes))


#: identification and labels, first in the table
KEYS = ("flight_id", "t", "label", "attack_type")

#: states, references and sensor values recorded per GPS step (ENU)
STATES = (
    Group("true_pos", XYZ, "m", "true position (simulation)"),
    Group("true_vel", XYZ, "m/s", "true velocity (simulation)"),
    Group("ref_pos", XYZ, "m", "mission reference position"),
    Group("est_pos", XYZ, "m", "filter estimate after this step's update"),
    Group("est_vel", XYZ, "m/s", "filter velocity estimate after this step's update"),
    Group("gps_pos", XYZ, "m", "GPS position as received (spoofed when label is 1)"),
    Group("gps_vel", XYZ, "m/s", "GPS velocity as received"),
    Group("vio_pos", XYZ, "m", "VIO position in its own drifting odometry frame"),
    Group("atk_d", XYZ, "m", "injected position offset d"),
    Group("wind", XYZ, "m/s", "wind at the vehicle (simulation)"),
)

#: the residues: what the filter's updates say at each GPS step
RESIDUES = (
    Group("res_gps_r", GPS_AXES, "m, m/s", "raw GPS innovation z - h(x)"),
    Group("res_gps_w", GPS_AXES, "1", "whitened GPS innovation L^-1 r, S = L L^T"),
    Group("res_gps_s", GPS_AXES, "m, m/s", "predicted innovation std sqrt(diag S)"),
    Group("res_gps_nis", (), "1", "GPS normalised innovation squared r^T S^-1 r (chi-square, 6 dof, nominal)"),
    Group("res_gps_corr", ("px", "py", "pz"), "m",
          "leaky integral (20 s) of the position corrections GPS updates applied"),
    Group("res_vio_r", VIO_AXES, "m/s, rad", "latest VIO innovation"),
    Group("res_vio_nis", (), "1", "latest VIO NIS"),
    Group("res_vio_nis_mean", (), "1", "mean VIO NIS since the previous GPS step"),
    Group("res_mag_r", ("yaw",), "rad",
          "latest magnetometer heading innovation: measured minus estimated heading, in [-pi, pi)"),
    Group("res_mag_nis", (), "1", "latest magnetometer heading NIS (chi-square, 1 dof, nominal)"),
    Group("res_baro_r", ("z",), "m", "latest barometric height innovation"),
    Group("res_baro_nis", (), "1", "latest barometric height NIS (chi-square, 1 dof, nominal)"),
    # persistent residues (estimator/reference.py): evidence that lasts as long as the spoof
    Group("res_gps_corr5", ("px", "py", "pz"), "m",
          "leaky integral (5 s) of the position corrections GPS updates applied"),
    Group("res_gps_corr120", ("px", "py", "pz"), "m",
          "leaky integral (120 s) of the position corrections GPS updates applied"),
    Group("res_ref_d", GPS_AXES, "m, m/s",
          "GPS minus the GPS-free reference (IMU + VIO, or IMU + barometer without VIO), smoothed (1 s), "
          "minus its anchor (its value 3 s earlier while GPS agrees, frozen while it disagrees)"),
    Group("res_ref_w", GPS_AXES, "1",
          "GPS minus the GPS-free reference (IMU + VIO, or IMU + barometer without VIO), smoothed (1 s), "
          "minus its anchor (its value when GPS last agreed), whitened by the reference's covariance growth "
          "since the anchor, the smoothed GPS noise and the GPS's slow error change; a spoof stays in it"),
    Group("res_ref_h5", GPS_AXES, "1",
          "change over the last 5 s of GPS minus the GPS-free reference (smoothed), whitened likewise"),
    Group("res_ref_h30", GPS_AXES, "1",
          "change over the last 30 s of GPS minus the GPS-free reference (smoothed), whitened likewise"),
    Group("res_ref_vmean", XYZ, "1",
          "GPS velocity minus the GPS-free reference's velocity averaged over 10 s, whitened by the "
          "averaged GPS velocity noise and the reference's velocity variance; a spoofed drift stays in it"),
    Group("res_ref_age", (), "s",
          "seconds since the anchor's value: about 3 s while GPS agrees with the reference, growing while "
          "it disagrees"),
    Group("res_gps_pv", XYZ, "1",
          "GPS velocity averaged over 5 s minus the change of GPS position over those 5 s per second, "
          "whitened by the GPS noise; a spoofed position without the matching velocity stays in it"),
    Group("res_ref_reset", GPS_AXES, "m, m/s",
          "the GPS-free reference's offset from its continuation without its resets to the main filter, "
          "less the offsets res_ref_d takes out at those resets (for the shape typer, not a detector input)"),
)

#: the persistent residues, in table order (after every other residue but ``res_ref_reset``, which
#: the shape typer reads and no detector)
PERSISTENT = ("res_gps_corr5", "res_gps_corr120", "res_ref_d", "res_ref_w", "res_ref_h5", "res_ref_h30",
              "res_ref_vmean", "res_ref_age", "res_gps_pv")

#: the groups of each aiding sensor: absent when the configuration leaves the sensor out
SENSOR_GROUPS = {
    "vio": ("vio_pos", "res_vio_r", "res_vio_nis", "res_vio_nis_mean"),
    "mag": ("res_mag_r", "res_mag_nis"),
    "baro": ("res_baro_r", "res_baro_nis"),
}

GROUPS = {g.name: g for g in STATES + RESIDUES}


def groups_for(sensors: str) -> tuple[Group, ...]:
    """The state and residue groups, in table order, of the flights of a sensor configuration
    such as ``"gps+imu+mag+baro"`` (``config.SENSOR_CONFIGS``)."""
    present = parse_sensors(sensors).split("+")
    absent = {g for sensor, groups in SENSOR_GROUPS.items() if sensor not in present for g in groups}
    return tuple(g for g in STATES + RESIDUES if g.name not in absent)


def columns(*groups: str) -> list[str]:
    """Column names of the named groups, in order."""
    out: list[str] = []
    for g in groups:
        try:
            out += GROUPS[g].columns
        except KeyError:
            raise KeyError(f"unknown column group {g!r}; known: {', '.join(GROUPS)}") from None
    return out


RESIDUE_COLUMNS = columns(*(g.name for g in RESIDUES))
NIS = "res_gps_nis"
WHITENED = columns("res_gps_w")

#: default inputs of the learned detectors: every residue except the predicted innovation std
#: (``res_gps_s_*``), which varies slowly with the flight's conditions and lets a network
#: recognise flights instead of attacks. A detector reads those present in its data; the
#: magnetometer and barometer come after them, then the persistent residues, so the order of
#: the earlier ones never changes.
DETECTOR_FEATURES = columns("res_gps_r", "res_gps_w", "res_gps_nis", "res_gps_corr", "res_vio_r",
                            "res_vio_nis", "res_vio_nis_mean", "res_mag_r", "res_mag_nis", "res_baro_r",
                            "res_baro_nis", *PERSISTENT)


def axis_columns(axis: str) -> list[str]:
    """Residue columns that point along world axis ``axis`` ('x', 'y' or 'z'), in the same
    order for every axis, and for 'z' the barometric height innovation after them: the
    columns that flip sign when the axis does."""
    cols = [f"res_gps_r_p{axis}", f"res_gps_r_v{axis}", f"res_gps_w_p{axis}", f"res_gps_w_v{axis}",
            f"res_gps_corr_p{axis}", f"res_vio_r_v{axis}", f"res_gps_corr5_p{axis}", f"res_gps_corr120_p{axis}",
            *(f"{g}_{k}{axis}" for g in ("res_ref_d", "res_ref_w", "res_ref_h5", "res_ref_h30") for k in "pv"),
            f"res_ref_vmean_{axis}", f"res_gps_pv_{axis}"]
    return cols + ["res_baro_r_z"] if axis == "z" else cols


def as_columns(groups: dict[str, object]) -> dict[str, object]:
    """{group: (n, width) array} -> {column: (n,) array}, for the groups present: the one place
    residue groups become the flight table's columns (a group outside ``GROUPS`` of width 3 gets
    the columns NAME_x, NAME_y, NAME_z; a time entry ``t`` is left out)."""
    out = {}
    for name, val in groups.items():
        if name == "t":
            continue
        cols = GROUPS[name].columns if name in GROUPS else [f"{name}_{a}" for a in "xyz"]
        for i, c in enumerate(cols):
            out[c] = val[:, i]
    return out
