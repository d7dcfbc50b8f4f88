"""``process.white``: white force/disturbance noise w_k entering the plant through L.

* ``std``: per-sample standard deviation of w_k, held over the sample (a zero-order-held input):
  x_{k+1} += G_d w_k with G_d = int_0^Ts e^{A s} ds L (zoh) or Ts L (euler, as the seed lesson).
* ``psd``: continuous two-sided intensity q of w(t) (units^2 s), E[w(t) w(s)] = q delta(t - s):
  x_{k+1} += e_k with Cov(e_k) = Q_d from Van Loan's formula (zoh) or L q L^T Ts (euler).
"""

from __future__ import annotations

import numpy as np

from .. import discretize
from ..errors import ModelError
from ..schema import nonnegative
from .base import Effect, FitSpec, _g, band_phrase


class ProcessWhite(Effect):
    id = "process.white"
    stage = "process"
    chain_order = 0
    draw_order = 2
    summary = "white process (force) noise through L"
    fit = FitSpec("noise", scale="std")
    # -- diagnosis hooks (base module docstring)
    channels = "noise_input"

    @classmethod
    def explain(cls, params, Ts, ctx=None):
        what = f"std {_g(params['std'])} per sample" if "std" in params else f"intensity {_g(params['psd'])}"
        return (f"{band_phrase(ctx)}excess power with the shape of the plant's response to a force "
                f"at its noise input: white process noise of {what}")

    @classmethod
    def equivalents(cls, params, Ts):
        """A force held over each sample with std s and continuous white noise of two-sided
        intensity q put the same power into the plant when q = s^2 Ts (G_d ~ Ts L, Q_d ~ L q L^T Ts)."""
        from .base import _map
        if "std" in params:
            return {"psd": _map(lambda s: s * s * Ts, params["std"])}
        return {"std": _map(lambda q: float(np.sqrt(q / Ts)), params["psd"])}

    def parse(self, t):
        if t.has("std") == t.has("psd"):
            raise t.error("std", "give exactly one of std (per-sample std) or psd (continuous intensity)")
        key = "std" if t.has("std") else "psd"
        self.mode = key
        self.params[key] = t.vector(key, self.dims.nw, check=nonnegative, expect="values >= 0")
        self._S = None
        self._source = t.source

    def process_factor(self, Ac: np.ndarray, L: np.ndarray) -> np.ndarray:
        """S with x_{k+1} += S e_k, e_k standard normal (n_x, n_e)."""
        Ts, disc = self.dims.Ts, self.dims.discretization
        if self.mode == "std":
            if disc == "euler":
                Gd = Ts * L
            else:
                _, Gd = discretize.zoh(Ac, L, Ts)
            S = Gd * self.params["std"]
            if not np.all(np.isfinite(S)):
                raise ModelError(f"{self._source}: [process.white] std: expected a process-noise input "
                                 f"G_d std that is finite over Ts = {Ts:g} ({disc}), got an overflow")
            return S
        Qc = L @ np.diag(self.params["psd"]) @ L.T
        Qd = discretize.euler_noise(Qc, Ts) if disc == "euler" else discretize.van_loan(Ac, Qc, Ts)
        if not np.all(np.isfinite(Qd)):   # psd_sqrt (eigh) would fail with LinAlgError
            raise ModelError(f"{self._source}: [process.white] psd: expected a process-noise covariance "
                             f"Q_d that is finite over Ts = {Ts:g} ({disc}), got an overflow "
                             "(psd or the plant's A Ts too large for float64)")
        return discretize.psd_sqrt(Qd)

    def bind(self, Ac: np.ndarray, L: np.ndarray) -> np.ndarray:
        """The factor of the assembled plant (``Ac``, ``L``), kept for :meth:`n_normals` and returned."""
        self._S = self.process_factor(Ac, L)
        return self._S

    def n_normals(self) -> int:
        return self._S.shape[1]
