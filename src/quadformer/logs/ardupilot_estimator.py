"""The ArduPilot reader's estimator streams: EKF3's GPS innovations and test ratios (``XKF3``,
``XKF4``) and the position estimate (``XKF1``), both of the primary core through lane switches."""

from __future__ import annotations

import numpy as np

from quadformer.geometry import frames
from quadformer.logs._series import median_period, nearest_index, step_lookup, take
from quadformer.logs.ardupilot_messages import DataflashMessages, col
from quadformer.logs.flightlog import make_stream

__all__ = ["DataflashEstimator"]


class DataflashEstimator(DataflashMessages):
    """The streams of ArduPilot's EKF cores: innovations and estimate."""

    # ------------------------------------------------------------ EKF cores
    def cores(self) -> dict:
        """Primary-core signal from XKF4.PI and the core field name per message."""
        x4 = self.rows["XKF4"]
        info = {"field": {}}
        for name in ("XKF1", "XKF3", "XKF4"):
            rows = self.rows[name]
            info["field"][name] = next((f for f in ("C", "Core") if rows and f in rows[0]), None)
        if x4 and "PI" in x4[0]:
            t = self.t(x4)
            order = np.argsort(t, kind="stable")
            info["t"], info["primary"] = t[order], col(x4, "PI")[order]
            switches = np.flatnonzero(np.diff(info["primary"]) != 0)
            if len(switches):
                self.notes.append("innovations/estimate: primary EKF core switched at t = "
                                  + ", ".join(f"{info['t'][i + 1]:.3f}" for i in switches[:10])
                                  + " s")
        else:
            info["t"], info["primary"] = np.array([0.0]), np.array([0.0])
            if x4:
                self.notes.append("innovations/estimate: XKF4 has no PI (primary core) field; "
                                  "core 0 used")
        return info

    def primary_rows(self, name: str, cores: dict, label: str) -> tuple[list[dict], np.ndarray]:
        rows = self.rows[name]
        field = cores["field"][name]
        if not rows:
            return [], np.array([])
        t = self.t(rows)
        core = col(rows, field) if field else np.zeros(len(rows))
        if field is None:
            self.notes.append(f"{label}: {name} has no core field; all rows taken as core 0")
        keep = core == step_lookup(t, cores["t"], cores["primary"])
        ids = sorted(set(core.tolist()))
        if len(ids) > 1:
            self.notes.append(f"{label}: {name} logged for EKF cores {[int(i) for i in ids]}; "
                              "kept the primary core's rows")
        return [r for r, k in zip(rows, keep) if k], core[keep]

    def innovations(self, cores: dict):
        rows, core = self.primary_rows("XKF3", cores, "innovations")
        if not rows:
            ekf2 = " (EKF2 NKF* messages are present but not read)" if self.rows["NKF3"] else ""
            self.notes.append(f"innovations: no XKF3 (EKF3) messages{ekf2}")
            return None
        self.require(rows, "XKF3", ("IPN", "IPE", "IPD", "IVN", "IVE", "IVD"))
        t = self.t(rows)
        pos = frames.ned_to_enu(np.column_stack([col(rows, k) for k in ("IPN", "IPE", "IPD")]))
        vel = frames.ned_to_enu(np.column_stack([col(rows, k) for k in ("IVN", "IVE", "IVD")]))
        values = {"pos_x": pos[:, 0], "pos_y": pos[:, 1], "pos_z": pos[:, 2],
                  "vel_x": vel[:, 0], "vel_y": vel[:, 1], "vel_z": vel[:, 2]}
        x4 = self.rows["XKF4"]
        if x4 and all(k in x4[0] for k in ("SV", "SP", "SH")):
            j = self._same_core_nearest(t, core, x4, cores["field"]["XKF4"])
            for src, dst in (("SP", "ratio_pos"), ("SV", "ratio_vel"), ("SH", "ratio_hgt")):
                values[dst] = take(col(x4, src) ** 2, j)
            self.notes.append("innovations: ratio_pos/vel/hgt = XKF4 SP^2/SV^2/SH^2 (logged as "
                              "square roots of the test ratios); variances are not logged")
        return make_stream("innovations", t, values, self.notes)

    def _same_core_nearest(self, t: np.ndarray, core: np.ndarray, rows: list[dict],
                           field: str | None) -> np.ndarray:
        ts = self.t(rows)
        rc = col(rows, field) if field else np.zeros(len(rows))
        j = np.full(len(t), -1)
        for c in np.unique(core):
            idx = np.flatnonzero(rc == c)
            if not len(idx):
                continue
            order = idx[np.argsort(ts[idx], kind="stable")]
            k = nearest_index(t[core == c], ts[order], 0.5 * median_period(ts[order]))
            j[core == c] = np.where(k >= 0, order[np.clip(k, 0, None)], -1)
        return j

    def estimate(self, cores: dict):
        rows, core = self.primary_rows("XKF1", cores, "estimate")
        if not rows:
            self.notes.append("estimate: no XKF1 messages")
            return None
        self.require(rows, "XKF1", ("PN", "PE", "PD", "VN", "VE", "VD"))
        t = self.t(rows)
        pos = frames.ned_to_enu(np.column_stack([col(rows, k) for k in ("PN", "PE", "PD")]))
        vel = frames.ned_to_enu(np.column_stack([col(rows, k) for k in ("VN", "VE", "VD")]))
        reset = np.zeros(len(t), bool)
        reset[1:] |= np.diff(core) != 0
        x4 = self.rows["XKF4"]
        if x4 and "OFN" in x4[0] and "OFE" in x4[0]:
            j = self._same_core_nearest(t, core, x4, cores["field"]["XKF4"])
            off = take(np.column_stack([col(x4, "OFN"), col(x4, "OFE")]), j)
            same_core = np.concatenate([[False], np.diff(core) == 0])
            changed = np.concatenate([[False], np.any(np.diff(off, axis=0) != 0, axis=1)])
            changed &= same_core & np.isfinite(off).all(axis=1) & \
                np.concatenate([[False], np.isfinite(off[:-1]).all(axis=1)])
            reset |= changed
        if reset.any():
            self.notes.append(f"estimate: {int(reset.sum())} position resets (core switch or "
                              "XKF4 OFN/OFE change) at t = "
                              + ", ".join(f"{v:.3f}" for v in t[reset][:10]) + " s")
        return make_stream("estimate", t, {"x": pos[:, 0], "y": pos[:, 1], "z": pos[:, 2],
                                           "vx": vel[:, 0], "vy": vel[:, 1], "vz": vel[:, 2],
                                           "reset": reset})
