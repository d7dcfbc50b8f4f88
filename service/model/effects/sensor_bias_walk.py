"""``sensor.bias_walk``: bias random walk (seed sections 2 and 6.2).

b_{k+1} = b_k + std sqrt(Ts) eta_k, eta_k ~ N(0, 1), so Q_b = std^2 Ts per sample and
Var(b_k) = Var(b_0) + k Q_b (seed section 6.2); ``std`` is in output units / sqrt(s) (the rate
random-walk coefficient K). ``initial_std`` (optional, default 0) is the std of b_0.
Nonstationary: it is reported as ``bias_var_rate`` = std^2 per second, not in the steady state.

``std`` is IEEE Std 952's K (rate random walk of a gyro, acceleration random walk of an
accelerometer; Kalibr's ``*_random_walk``): the bias is the integral of white noise of two-sided
PSD K^2, so its rate PSD is K^2 / (2 pi f)^2 and the Allan deviation climbs as

    sigma_A(tau) = K sqrt(tau / 3),      K = std                 (IEEE Std 952-1997, Annex C;
                                                                  El-Sheimy et al. 2008, table 1)

read where the +1/2 slope line crosses tau = 3 s. Its unit is units/sqrt(s), the same as the
units/s/sqrt(Hz) data sheets write (rad/s^2/sqrt(Hz) for a gyro in rad/s).
"""

from __future__ import annotations

import numpy as np

from ..schema import nonnegative
from .base import Coefficient, Effect, FitSpec, _g


class SensorBiasWalk(Effect):
    id = "sensor.bias_walk"
    stage = "sensor"
    chain_order = 7
    draw_order = 3
    summary = "sensor bias random walk (drift)"
    fit = FitSpec("noise", scale="std")
    # -- diagnosis hooks (base module docstring)
    channels = "output"
    drift = "sensor"

    @classmethod
    def explain(cls, params, Ts, ctx=None):
        band = (ctx or {}).get("band")
        where = f"below {_g(band[1])} Hz " if band else "at low frequency "
        return (f"{where}the PSD rises as 1/f^2 and the Allan deviation climbs with slope +1/2 at long "
                f"averaging times: a bias random walk of about {_g(params['std'])} per sqrt(s)")

    def parse(self, t):
        self.params["std"] = t.vector("std", self.dims.p, check=nonnegative, expect="std >= 0 in units/sqrt(s)")
        init = t.vector("initial_std", self.dims.p, None, check=nonnegative, expect="std >= 0")
        if init is not None:
            self.params["initial_std"] = init
        self.init_std = np.zeros(self.dims.p) if init is None else init
        self.q_step = self.params["std"] * np.sqrt(self.dims.Ts)   # sqrt(Q_b)

    def coefficients(self):
        return [Coefficient("K", self.params["std"], "{u}/sqrt(s)", "std", lambda s: np.asarray(s, float))]

    def n_normals(self):
        return self.dims.p

    def init_state(self, static_rng, trials):
        b0 = self.init_std * static_rng.standard_normal((trials, self.dims.p)) if np.any(self.init_std) \
            else np.zeros((trials, self.dims.p))
        return {"b": b0}

    def sensor_terms(self, e, state):
        # b_k = b_{k-1} + q eta_{k-1}: a sequential cumulative sum started from the carried bias,
        # the same additions in the same order as sensor_step (identical floats)
        inc = self.q_step * e
        b = np.cumsum(np.concatenate([state["b"][:, None, :], inc], axis=1), axis=1)
        state["b"] = b[:, -1, :].copy()
        return b[:, :-1, :]

    def spectral(self):
        return [("walk", self.params["std"] ** 2 * self.dims.Ts, self.init_std**2)]
