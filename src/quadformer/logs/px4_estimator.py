"""The PX4 reader's estimator streams: EKF2's GPS innovations (of the primary instance) with their
variances and test ratios, the local position estimate about the autopilot's origin, the attitude."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from quadformer.geometry import frames
from quadformer.logs._series import median_period, nearest_index, row_max, step_lookup, take
from quadformer.logs.flightlog import make_stream
from quadformer.logs.px4_topics import UlogTopics

__all__ = ["UlogEstimator"]


class UlogEstimator(UlogTopics):
    """The streams of PX4's estimator: innovations, estimate and attitude."""

    def primary_mask(self, label: str, t: np.ndarray, instance: int, n_instances: int) -> np.ndarray:
        sel = self.dataset("estimator_selector_status")
        if n_instances <= 1:
            return np.ones(len(t), bool)
        if sel is None:
            return np.full(len(t), instance == 0)
        st = self.times(sel, "estimator_selector_status", use_sample=False)
        ok = np.isfinite(st)
        primary = self.field(sel, "primary_instance")[ok]
        return step_lookup(t, st[ok], primary) == instance

    def innovations(self):
        inst = self.instances("estimator_innovations")
        if inst:
            return self._innovations_new(inst)
        d = self.dataset("ekf2_innovations")
        if d is not None:
            return self._innovations_old(d)
        self.notes.append("innovations: no estimator_innovations or ekf2_innovations topic")
        return None

    def _match(self, t: np.ndarray, name: str, multi_id: int):
        """The dataset ``name`` of one instance and, per row time t, its nearest sample."""
        cand = [d for d in self.instances(name) if d.multi_id == multi_id]
        if not cand:
            return None, np.full(len(t), -1)
        d = cand[0]
        ts = self.times(d, "innovations", use_sample=True)
        ok = np.isfinite(ts)
        idx_ok = np.flatnonzero(ok)
        order = np.argsort(ts[ok], kind="stable")
        j = nearest_index(t, ts[ok][order], 0.5 * median_period(ts[ok][order]))
        return d, np.where(j >= 0, idx_ok[order][np.clip(j, 0, None)], -1)

    def _innovations_new(self, inst: list):
        parts, ids = [], [d.multi_id for d in inst]
        sel = self.dataset("estimator_selector_status")
        if len(inst) > 1:
            how = ("the primary instance per estimator_selector_status" if sel is not None
                   else "instance 0 (no estimator_selector_status)")
            self.notes.append(f"innovations: estimator instances {ids} logged; kept rows of {how}")
        for d in inst:
            t = self.times(d, "innovations")
            rows = self.primary_mask("innovations", t, d.multi_id, len(inst))
            if not rows.any():
                continue
            hp = self.vector(d, "gps_hpos", 2)
            vp = self.field(d, "gps_vpos").astype(float)
            hv = self.vector(d, "gps_hvel", 2)
            vv = self.field(d, "gps_vvel").astype(float)
            pos = frames.ned_to_enu(np.column_stack([hp, vp]))
            vel = frames.ned_to_enu(np.column_stack([hv, vv]))
            values = {"pos_x": pos[:, 0], "pos_y": pos[:, 1], "pos_z": pos[:, 2],
                      "vel_x": vel[:, 0], "vel_y": vel[:, 1], "vel_z": vel[:, 2]}
            dv, j = self._match(t, "estimator_innovation_variances", d.multi_id)
            if dv is not None:
                pv = frames.ned_var_to_enu(take(np.column_stack(
                    [self.vector(dv, "gps_hpos", 2), self.field(dv, "gps_vpos")]), j))
                vvar = frames.ned_var_to_enu(take(np.column_stack(
                    [self.vector(dv, "gps_hvel", 2), self.field(dv, "gps_vvel")]), j))
                for k, a in enumerate("xyz"):
                    values[f"var_pos_{a}"] = pv[:, k]
                    values[f"var_vel_{a}"] = vvar[:, k]
            dr, j = self._match(t, "estimator_innovation_test_ratios", d.multi_id)
            if dr is not None:
                values["ratio_pos"] = take(row_max(self.vector(dr, "gps_hpos", 2)), j)
                values["ratio_hgt"] = take(self.field(dr, "gps_vpos"), j)
                values["ratio_vel"] = take(row_max(np.column_stack(
                    [self.vector(dr, "gps_hvel", 2), self.field(dr, "gps_vvel")])), j)
            parts.append(make_stream("innovations", t, values)[rows])
        if not parts:
            self.notes.append("innovations: no rows from the primary estimator instance")
            return None
        if not self.instances("estimator_innovation_variances"):
            self.notes.append("innovations: no estimator_innovation_variances; variances NaN")
        if not self.instances("estimator_innovation_test_ratios"):
            self.notes.append("innovations: no estimator_innovation_test_ratios; ratios NaN")
        out = pd.concat(parts, ignore_index=True) if len(parts) > 1 else parts[0]
        return out.sort_values("t", kind="stable").reset_index(drop=True)

    def _innovations_old(self, d):
        t = self.times(d, "innovations")
        innov = self.vector(d, "vel_pos_innov", 6)
        var = self.vector(d, "vel_pos_innov_var", 6, required=False)
        vel, pos = frames.ned_to_enu(innov[:, :3]), frames.ned_to_enu(innov[:, 3:])
        values = {"pos_x": pos[:, 0], "pos_y": pos[:, 1], "pos_z": pos[:, 2],
                  "vel_x": vel[:, 0], "vel_y": vel[:, 1], "vel_z": vel[:, 2]}
        if var is not None:
            vv, pv = frames.ned_var_to_enu(var[:, :3]), frames.ned_var_to_enu(var[:, 3:])
            for k, a in enumerate("xyz"):
                values[f"var_pos_{a}"] = pv[:, k]
                values[f"var_vel_{a}"] = vv[:, k]
        ds, j = self._match(t, "estimator_status", 0)
        if ds is not None:
            for col, f in (("ratio_pos", "pos_test_ratio"), ("ratio_vel", "vel_test_ratio"),
                           ("ratio_hgt", "hgt_test_ratio")):
                src = self.field(ds, f, required=False)
                if src is not None:
                    values[col] = take(src, j)
        self.notes.append("innovations: old ekf2_innovations (velocity/position innovations of "
                          "the fused aiding source); test ratios from estimator_status")
        return make_stream("innovations", t, values)

    def local_position(self):
        d = self.dataset("vehicle_local_position")
        if d is None:
            self.notes.append("estimate: no vehicle_local_position topic")
            return None, None
        t = self.times(d, "estimate")
        ned = np.stack([self.field(d, k).astype(float) for k in ("x", "y", "z")], axis=-1)
        vel = np.stack([self.field(d, k).astype(float) for k in ("vx", "vy", "vz")], axis=-1)
        ref = np.stack([d.data[k].astype(float) if k in d.data else np.full(len(t), np.nan)
                        for k in ("ref_lat", "ref_lon", "ref_alt")], axis=-1)
        valid = np.isfinite(ref).all(axis=1) & ~((ref[:, 0] == 0) & (ref[:, 1] == 0))
        valid &= (np.abs(ref[:, 0]) <= 90) & (np.abs(ref[:, 1]) <= 180)
        xy_global = self.field(d, "xy_global", required=False)
        if xy_global is not None:
            valid &= xy_global != 0
        reset = np.zeros(len(t), bool)
        for k in ("xy_reset_counter", "z_reset_counter"):
            c = self.field(d, k, required=False)
            if c is not None and len(c) > 1:
                reset[1:] |= np.diff(c.astype(np.int64)) != 0
        raw = {"t": t, "ned": ned, "vel": frames.ned_to_enu(vel), "ref": ref, "valid": valid,
               "reset": reset}
        if reset.any():
            dxy = self.vector(d, "delta_xy", 2, required=False)
            dz = self.field(d, "delta_z", required=False)
            big_xy = row_max(np.hypot(dxy[reset, 0], dxy[reset, 1])[None])[0] \
                if dxy is not None else np.nan
            big_z = row_max(np.abs(dz[reset])[None].astype(float))[0] if dz is not None else np.nan
            self.notes.append(f"estimate: {int(reset.sum())} position resets (reset counters) at t = "
                              + ", ".join(f"{v:.3f}" for v in t[reset][:10])
                              + f" s; largest |delta_xy| {big_xy:.3f} m, |delta_z| {big_z:.3f} m")
        if not valid.any():
            self.notes.append("estimate: the autopilot logged no local origin (ref_lat/ref_lon "
                              "unset); positions are in the estimator's own local frame")
            return raw, None
        origin = tuple(float(v) for v in ref[np.argmax(valid)])
        return raw, origin

    def estimate_stream(self, raw: dict | None, origin):
        if raw is None:
            return None
        pos = frames.ned_to_enu(raw["ned"])
        reset = raw["reset"].copy()
        valid = raw["valid"]
        if valid.any() and all(math.isfinite(v) for v in origin):
            refs, inverse = np.unique(raw["ref"][valid], axis=0, return_inverse=True)
            offsets = frames.geodetic_to_enu(refs[:, 0], refs[:, 1], refs[:, 2], origin)
            pos[valid] += offsets[inverse.reshape(-1)]
            if len(refs) > 1:
                idx = np.flatnonzero(valid)
                moved = idx[1:][np.any(raw["ref"][idx[1:]] != raw["ref"][idx[:-1]], axis=1)]
                reset[moved] = True
                self.notes.append(f"estimate: the local origin moved {len(moved)} times; positions "
                                  "re-expressed about the first origin and marked as resets")
            own = int((~valid).sum())
            if own:
                self.notes.append(f"estimate: {own} samples before the local origin was set are in "
                                  "the estimator's own frame")
        return make_stream("estimate", raw["t"], {
            "x": pos[:, 0], "y": pos[:, 1], "z": pos[:, 2], "vx": raw["vel"][:, 0],
            "vy": raw["vel"][:, 1], "vz": raw["vel"][:, 2], "reset": reset})

    def attitude(self):
        d = self.dataset("vehicle_attitude")
        if d is None:
            self.notes.append("attitude: no vehicle_attitude topic")
            return None
        q = frames.quat_ned_frd_to_enu_flu(frames.wxyz_to_xyzw(self.vector(d, "q", 4)))
        return make_stream("attitude", self.times(d, "attitude"),
                           {"qx": q[:, 0], "qy": q[:, 1], "qz": q[:, 2], "qw": q[:, 3]})
