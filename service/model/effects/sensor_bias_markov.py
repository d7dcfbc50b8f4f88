"""``sensor.bias_markov``: first-order Gauss-Markov bias (bias instability).

Continuous beta' = -beta / tau + white, stationary std ``std``; exact discretization
beta_{k+1} = phi beta_k + std sqrt(1 - phi^2) xi_k with phi = exp(-Ts / tau_s). Starts at 0.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import lfilter

from ..schema import nonnegative
from .base import Effect, FitSpec, _g, parse_rho_tau, rho_tau_equivalents


class SensorBiasMarkov(Effect):
    id = "sensor.bias_markov"
    stage = "sensor"
    chain_order = 8
    draw_order = 4
    summary = "first-order Gauss-Markov sensor bias (bias instability)"
    fit = FitSpec("noise", scale="std", shape=(("tau_s", 2.0, 1.0, "Ts|T", "log"),))

    @classmethod
    def explain(cls, params, Ts, ctx=None):
        tau = params.get("tau_s")
        if tau is None:
            rho = np.atleast_1d(params["rho"]).astype(float)
            tau = float(np.mean(-Ts / np.log(rho)))
        fc = 1.0 / (2 * np.pi * np.mean(tau))
        return (f"a flat excess below about {_g(fc)} Hz that the plant does not shape, and an Allan "
                f"deviation bump near tau = {_g(1.9 * np.mean(tau))} s: a Gauss-Markov bias (bias instability) of std "
                f"{_g(params['std'])} with correlation time {_g(tau)} s")

    @classmethod
    def equivalents(cls, params, Ts):
        return rho_tau_equivalents(params, Ts)

    def parse(self, t):
        self.params["std"] = t.vector("std", self.dims.p, check=nonnegative, expect="std >= 0")
        phi, tau = parse_rho_tau(t, self.dims.p, self.dims.Ts)
        self.params["rho" if t.has("rho") else "tau_s"] = phi if t.has("rho") else tau
        self.phi = phi
        self.c = np.sqrt(1.0 - phi**2) * self.params["std"]

    def n_normals(self):
        return self.dims.p

    def init_state(self, static_rng, trials):
        return {"b": np.zeros((trials, self.dims.p))}

    def sensor_terms(self, e, state):
        # beta_k (before the update with xi_k) enters y_k
        out = np.empty_like(e)
        for j in range(self.dims.p):
            nxt, _ = lfilter([self.c[j]], [1.0, -self.phi[j]], e[..., j], axis=-1,
                             zi=(self.phi[j] * state["b"][:, j])[:, None])
            out[..., j] = np.concatenate([state["b"][:, j:j + 1], nxt[:, :-1]], axis=1)
            state["b"][:, j] = nxt[:, -1]
        return out

    def sensor_linear(self):
        return np.diag(self.phi), np.diag(self.c), np.eye(self.dims.p)
