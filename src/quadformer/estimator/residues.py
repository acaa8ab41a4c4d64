"""The residue generator: what the filter's updates say, per GPS step.

One ``ResidueTracker`` serves the closed loop and the replay of recorded sensor streams,
so both produce the same ``res_*`` features from the same innovations:

- GPS: raw innovation, whitened innovation (L^-1 r), sqrt(diag S), NIS;
- the leaky integral (time constant ``corr_tau``) of the position corrections GPS updates
  applied: how far GPS has recently pulled the estimate; a spoof the filter absorbs keeps it
  displaced until the spoof ends; the same at the time constants ``CORR_TAUS`` (5 s: a
  recent pull, 120 s: a pull that lasts as long as the spoof);
- VIO: the latest innovation and NIS, and the mean NIS since the previous GPS step;
- magnetometer: the latest heading innovation and its NIS;
- barometer: the latest height innovation and its NIS.

The groups of an aiding sensor are produced only when it is among ``aiding``.
"""

from __future__ import annotations

import numpy as np
import torch

from quadformer.estimator.eskf import Innovation
from quadformer.estimator.feed import AIDING
from quadformer.estimator.schema import CORR_TAU, CORR_TAUS


class ResidueTracker:
    def __init__(self, n: int, gps_rate_hz: float, corr_tau: float = CORR_TAU,
                 aiding: tuple[str, ...] = ("vio",)):
        unknown = [a for a in aiding if a not in AIDING]
        if unknown:
            raise ValueError(f"aiding: unknown sensor {unknown[0]!r}; choose from {', '.join(AIDING)}")
        z = lambda *s: torch.zeros(*s, dtype=torch.float64)  # noqa: E731
        self.aiding = tuple(a for a in AIDING if a in aiding)
        self.corr = z(n, 3)
        self.decay = float(np.exp(-1.0 / (gps_rate_hz * corr_tau)))
        self.corrs = {name: z(n, 3) for name in CORR_TAUS}
        self.decays = {name: float(np.exp(-1.0 / (gps_rate_hz * tau))) for name, tau in CORR_TAUS.items()}
        self.vio_r, self.vio_nis = z(n, 6), z(n)
        self._sum, self._count = z(n), 0
        self.mag_r, self.mag_nis = z(n, 1), z(n)
        self.baro_r, self.baro_nis = z(n, 1), z(n)

    def on_vio(self, inn: Innovation) -> None:
        self.vio_r, self.vio_nis = inn.r, inn.nis
        self._sum = self._sum + inn.nis
        self._count += 1

    def on_mag(self, inn: Innovation) -> None:
        self.mag_r, self.mag_nis = inn.r, inn.nis

    def on_baro(self, inn: Innovation) -> None:
        self.baro_r, self.baro_nis = inn.r, inn.nis

    def on_gps(self, inn: Innovation) -> dict[str, torch.Tensor]:
        """Residues of this GPS step (each (n, k)); resets the VIO mean.

        The correction integral includes the correction the update proposes (``inn.dx``), as
        a filter that always fuses GPS applies it; see ``applied`` for one that does not."""
        proposed = self.decay * self.corr + inn.dx[:, 0:3]
        self.corr = proposed
        out = {"res_gps_r": inn.r, "res_gps_w": inn.w, "res_gps_s": inn.s_std, "res_gps_nis": inn.nis[:, None],
               "res_gps_corr": proposed}
        for name, decay in self.decays.items():
            self.corrs[name] = decay * self.corrs[name] + inn.dx[:, 0:3]
            out[name] = self.corrs[name]
        if "vio" in self.aiding:
            out.update(res_vio_r=self.vio_r, res_vio_nis=self.vio_nis[:, None],
                       res_vio_nis_mean=(self._sum / max(self._count, 1))[:, None])
        if "mag" in self.aiding:
            out.update(res_mag_r=self.mag_r, res_mag_nis=self.mag_nis[:, None])
        if "baro" in self.aiding:
            out.update(res_baro_r=self.baro_r, res_baro_nis=self.baro_nis[:, None])
        self._sum = torch.zeros_like(self._sum)
        self._count = 0
        return out

    def applied(self, proposed: torch.Tensor, applied: torch.Tensor) -> None:
        """After ``on_gps``: the position correction actually applied (n, 3) replaces the
        proposed one (n, 3) in the integral carried to later steps (resilient estimation
        excludes or rolls back GPS corrections). Flights where they are equal are unchanged."""
        same = (proposed == applied).all(-1, keepdim=True)
        self.corr = torch.where(same, self.corr, self.corr - proposed + applied)
        for name in self.corrs:
            self.corrs[name] = torch.where(same, self.corrs[name], self.corrs[name] - proposed + applied)
