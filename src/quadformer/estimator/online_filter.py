"""The filter state fed one timestamped sample at a time (``OnlineFilter``): each IMU sample
propagates, then the aiding samples and GPS fixes queued up to it are applied, each fix giving
one row of residues; ``GapError`` where the IMU has a gap the filter cannot propagate across."""

from __future__ import annotations

from collections import deque
from dataclasses import replace

import numpy as np
import torch

from quadformer.estimator.eskf import (
    EKFState,
    NoiseModel,
    baro_update,
    gps_update,
    mag_update,
    predict,
    vio_update,
)
from quadformer.estimator.feed import AIDING, EPS, GapError, StreamError
from quadformer.estimator.reference import GpsFreeReference
from quadformer.estimator.residues import ResidueTracker

__all__ = ["AIDING", "EPS", "GapError", "OnlineFilter", "StreamError"]


def _tensor(x) -> torch.Tensor:
    """A sample as a float64 tensor: a tensor as given, an array copied (the caller keeps it)."""
    return x if isinstance(x, torch.Tensor) else torch.from_numpy(np.array(x, dtype=np.float64))


class OnlineFilter:
    def __init__(self, ekf0: EKFState, nm: NoiseModel, dt: float, t0: float = 0.0, gps_rate_hz: float = 10.0,
                 aiding: tuple[str, ...] = (), max_gap: float = 0.1):
        unknown = [a for a in aiding if a not in AIDING]
        if unknown:
            raise ValueError(f"aiding: unknown sensor {unknown[0]!r}; choose from {', '.join(AIDING)}")
        self.ekf, self.nm, self.dt, self.t, self.max_gap = ekf0, nm, float(dt), float(t0), float(max_gap)
        self.n = ekf0.p.shape[0]
        self.aiding = tuple(a for a in AIDING if a in aiding)
        self.tracker = ResidueTracker(self.n, gps_rate_hz, aiding=self.aiding)
        self.reference = GpsFreeReference(ekf0, nm, gps_rate_hz, self.aiding)
        self.queues: dict[str, deque] = {name: deque() for name in (*self.aiding, "gps")}
        self._fuse = {"vio": lambda s, x: vio_update(s, x[:, 0:3], x[:, 3:7], self.nm),
                      "mag": lambda s, x: mag_update(s, x, self.nm), "baro": lambda s, x: baro_update(s, x, self.nm)}
        self._track = {"vio": self.tracker.on_vio, "mag": self.tracker.on_mag, "baro": self.tracker.on_baro}
        self._refer = {"vio": lambda x: self.reference.vio(x[:, 0:3]), "mag": lambda x: None,
                       "baro": self.reference.baro}

    # -- what the stream around it reads and sets ------------------------------------------
    @property
    def position(self):
        """The estimated position (n,3), ENU m, as numpy."""
        return self.ekf.p.numpy().copy()

    @property
    def mag_field(self):
        return None if self.nm.mag_field is None else self.nm.mag_field.numpy()

    def set_mag_field(self, field) -> None:
        """The Earth field (3,) (world, ENU) the magnetometer heading is measured against."""
        self.nm = replace(self.nm, mag_field=torch.as_tensor(field, dtype=torch.float64))

    # -- samples ------------------------------------------------------------------------
    def push(self, stream: str, t: float, x, std=None) -> None:
        """Queue an aiding or GPS sample (n, k) stamped t (a tensor or an array), applied at the
        first IMU step at or after t. ``std``: GPS only, the receiver's own std per flight (n, 6)."""
        if stream not in self.queues:
            raise ValueError(f"{stream}: not a stream of this filter (it fuses {', '.join(self.queues)})")
        self.queues[stream].append((float(t), _tensor(x), None if std is None else _tensor(std)))

    def imu(self, t: float, x) -> list[tuple[float, dict[str, torch.Tensor]]]:
        """Propagate to t with the IMU sample x (n, 6), then apply the queued samples stamped
        at or before t. Returns (stamp, residue row) per GPS fix applied; a row holds the
        residue groups and ``est_pos``, ``est_vel``, each (n, k)."""
        x = _tensor(x)
        step = t - self.t
        if step > self.max_gap:
            raise GapError(f"imu: gap of {step:.3f} s before t = {t:.3f} s (more than {self.max_gap} s); "
                           f"split the log there")
        h = self.dt if abs(step - self.dt) < EPS else float(step)
        self.reference.predict(self.ekf, x[:, 0:3], h)
        self.ekf = predict(self.ekf, x[:, 0:3], x[:, 3:6], h, self.nm)
        self.t = t
        for name in self.aiding:
            q = self.queues[name]
            while q and q[0][0] <= t + EPS:
                sample = q.popleft()[1]
                self.ekf, inn = self._fuse[name](self.ekf, sample)
                self._track[name](inn)
                self._refer[name](sample)
        rows = []
        q = self.queues["gps"]
        while q and q[0][0] <= t + EPS:
            stamp, fix, std = q.popleft()
            self.ekf, inn = gps_update(self.ekf, fix[:, 0:3], fix[:, 3:6], self.nm, std=std)
            res = {**self.tracker.on_gps(inn), **self.reference.on_gps(fix[:, 0:3], fix[:, 3:6], std)}
            self.reference.anchor(self.ekf)
            rows.append((stamp, {"est_pos": self.ekf.p, "est_vel": self.ekf.v, **res}))
        return rows

    @property
    def pending(self) -> int:
        """Samples queued and not yet applied (they wait for an IMU sample at or after them)."""
        return sum(len(q) for q in self.queues.values())
