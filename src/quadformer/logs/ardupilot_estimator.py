"""The ArduPilot reader's estimator streams: the GPS innovations and test ratios (EKF3's ``XKF3``,
``XKF4``; EKF2's and the first EKF's ``NKF*`` and ``EKF*`` alike) with the innovation variances
recovered from the ratios (``ardupilot_ratios``), and the position estimate (``XKF1``), both of
the primary core through lane switches. An estimator message of a layout without the fields read
is noted and left out, not an error."""

from __future__ import annotations

import numpy as np

from quadformer.geometry import frames
from quadformer.logs._series import median_period, nearest_index, step_lookup, take
from quadformer.logs.ardupilot_messages import DataflashMessages, col
from quadformer.logs.ardupilot_ratios import FAMILIES, ratio_model, recover_variances
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
        name3, name4 = (f"{self.ekf_family}3", f"{self.ekf_family}4")
        rows, core = self.primary_rows("XKF3", cores, "innovations")
        if not rows:
            self.notes.append("innovations: no XKF3, NKF3 or EKF3 messages (EKF3, EKF2 or the first EKF's "
                              "innovations)")
            return None
        missing = [f for f in ("IPN", "IPE", "IPD", "IVN", "IVE", "IVD") if f not in rows[0]]
        if missing:
            self.notes.append(f"innovations: {name3} lacks {', '.join(missing)} (has: {', '.join(sorted(rows[0]))}); "
                              "an estimator message layout this reader does not know: innovations not read")
            return None
        t = self.t(rows)
        pos = frames.ned_to_enu(np.column_stack([col(rows, k) for k in ("IPN", "IPE", "IPD")]))
        vel = frames.ned_to_enu(np.column_stack([col(rows, k) for k in ("IVN", "IVE", "IVD")]))
        values = {"pos_x": pos[:, 0], "pos_y": pos[:, 1], "pos_z": pos[:, 2],
                  "vel_x": vel[:, 0], "vel_y": vel[:, 1], "vel_z": vel[:, 2]}
        ratios = self._ratios(t, core, cores, name4)
        if ratios is not None:
            values.update(ratios)
            self._variances(values, name4)
        return make_stream("innovations", t, values, self.notes)

    def _ratios(self, t: np.ndarray, core: np.ndarray, cores: dict, name4: str) -> dict | None:
        """The test ratios of the same core at the innovations' times: SV, SP, SH squared (the
        square roots of the ratios; ``ardupilot_ratios``)."""
        x4 = self.rows["XKF4"]
        if not x4:
            self.notes.append(f"innovations: no {name4} messages: test ratios and innovation variances not read")
            return None
        lacking = [f for f in ("SV", "SP", "SH") if f not in x4[0]]
        if lacking:
            self.notes.append(f"innovations: {name4} lacks {', '.join(lacking)} (has: {', '.join(sorted(x4[0]))}); "
                              "test ratios and innovation variances not read")
            return None
        scale = 1.0
        chars = {self.field_format(name4, f) for f in ("SV", "SP", "SH")} - {None}
        if chars & set("bBhHiIqQ"):
            scale = 0.01
            self.notes.append(f"innovations: {name4} SV/SP/SH logged as unscaled integers ({''.join(sorted(chars))}), "
                              "not ArduPilot's int16 x 0.01 ('c'): read as 100 times the square roots")
        j = self._same_core_nearest(t, core, x4, cores["field"]["XKF4"])
        return {dst: take((scale * col(x4, src)) ** 2, j)
                for src, dst in (("SV", "ratio_vel"), ("SP", "ratio_pos"), ("SH", "ratio_hgt"))}

    def _variances(self, values: dict, name4: str) -> None:
        """The innovation variances ArduPilot does not log, recovered from the test ratios
        (``ardupilot_ratios.recover_variances``), into ``values``."""
        gpa = self.rows["GPA"]
        first = min((r.get("I", 0) for r in gpa), default=0)          # the receiver the gps stream keeps
        vv = col([r for r in gpa if r.get("I", 0) == first], "VV")
        receiver_vz = not (vv == 0).any()
        model = ratio_model(self.ekf_family, self.params(), self.firmware(), receiver_vz)
        innov = np.column_stack([values[k] for k in ("pos_x", "pos_y", "pos_z", "vel_x", "vel_y", "vel_z")])
        var, empty = recover_variances(innov, values, model)
        for k, c in enumerate(("var_pos_x", "var_pos_y", "var_pos_z", "var_vel_x", "var_vel_y", "var_vel_z")):
            values[c] = var[:, k]
        self.notes.append(f"innovations: ratio_vel/pos/hgt = {name4} SV^2/SP^2/SH^2 (logged as the square roots of "
                          f"{FAMILIES[self.ekf_family]}'s test ratios); variances recovered from the test ratios, "
                          + "; ".join(model.notes)
                          + "; each group's summed variance shared equally among its axes")
        n = len(innov)
        if any(empty.values()):
            self.notes.append("innovations: steps whose ratio is 0 or NaN or whose innovations are all 0 hold no "
                              "variance, left unfused: " + ", ".join(f"{g} {k} of {n}" for g, k in empty.items() if k))

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
        missing = [f for f in ("PN", "PE", "PD", "VN", "VE", "VD") if f not in rows[0]]
        if missing:
            self.notes.append(f"estimate: {self.ekf_family}1 lacks {', '.join(missing)} (has: "
                              f"{', '.join(sorted(rows[0]))}); an estimator message layout this reader does not "
                              "know: the estimate not read")
            return None
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
