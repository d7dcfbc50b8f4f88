"""``actuator.ar1``: colored actuator noise, an AR(1) process (seed sections 2, 5 and 10).

n_{k+1} = rho n_k + e_k,  Var(e_k) = (1 - rho^2) std^2  (seed section 5, sigma_e^2 = (1-rho^2) sigma_n^2)
so the stationary std is ``std``; rho = exp(-Ts / tau_s) when ``tau_s`` is given. As in the seed the
noise is updated before it is used: the input at sample k carries n_{k+1}. It starts at 0.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import lfilter

from ..schema import nonnegative
from .base import Effect, FitSpec, _g, parse_rho_tau, rho_tau_equivalents, tau_of


class ActuatorAR1(Effect):
    id = "actuator.ar1"
    stage = "actuator"
    chain_order = 2
    draw_order = 1
    summary = "colored (AR(1)) actuator noise in the input channel"
    fit = FitSpec("noise", scale="std", shape=(("tau_s", 0.5, 2.0, "Ts|T", "log"),), replaces=("actuator.white",))
    # -- diagnosis hooks (base module docstring)
    channels = "input"
    drift = "actuator"

    @classmethod
    def explain(cls, params, Ts, ctx=None):
        tau = tau_of(params, Ts)
        if not np.all(np.isfinite(tau)):
            return (f"excess power that alternates from sample to sample: colored (AR(1)) actuator noise of "
                    f"std {_g(params['std'])} with rho {_g(params['rho'])}")
        fc = 1.0 / (2 * np.pi * tau)
        return (f"excess power below about {_g(fc if fc.size > 1 else fc[0])} Hz that the plant shapes like its "
                f"input: colored (AR(1)) actuator noise of std {_g(params['std'])} with correlation time "
                f"{_g(tau if tau.size > 1 else tau[0])} s")

    @classmethod
    def equivalents(cls, params, Ts):
        return rho_tau_equivalents(params, Ts)

    def parse(self, t):
        self.params["std"] = t.vector("std", self.dims.m, check=nonnegative, expect="std >= 0")
        rho, tau = parse_rho_tau(t, self.dims.m, self.dims.Ts)
        self.rho = rho
        self.params["rho" if t.has("rho") else "tau_s"] = rho if t.has("rho") else tau
        # innovation std: sigma_e = sqrt(1 - rho^2) sigma_n
        self.c = np.sqrt(1.0 - rho**2) * self.params["std"]

    def n_normals(self):
        return self.dims.m

    def init_state(self, static_rng, trials):
        return {"n": np.zeros((trials, self.dims.m))}

    def actuator_terms(self, e, state):
        """n_{k+1} = rho n_k + c e_k per channel, for a block of normals e (trials, n, m); the
        input at sample k carries n_{k+1}. The state n is carried between blocks."""
        out = np.empty_like(e)
        for j in range(self.dims.m):
            out[..., j], _ = lfilter([self.c[j]], [1.0, -self.rho[j]], e[..., j], axis=-1,
                                      zi=(self.rho[j] * state["n"][:, j])[:, None])
        state["n"] = out[:, -1, :].copy()
        return out

    def drive_linear(self):
        return np.diag(self.rho), np.diag(self.c), np.diag(self.rho), np.diag(self.c)
