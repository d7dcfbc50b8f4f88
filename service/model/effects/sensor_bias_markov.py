"""``sensor.bias_markov``: first-order Gauss-Markov bias (an exponentially correlated drift).

Continuous beta' = -beta / tau + white, stationary std ``std``; exact discretization
beta_{k+1} = phi beta_k + std sqrt(1 - phi^2) xi_k with phi = exp(-Ts / tau_s). Starts at 0.

Its coefficients are the process's own, ``sigma_GM`` = std (output units) and ``tau_GM`` = tau_s
(s), not IEEE Std 952's bias instability B: B is the flicker (1/f) floor of the Allan deviation,
sigma_A = sqrt(2 ln 2 / pi) B ~ 0.664 B over a range of tau, which one Gauss-Markov process only
approximates near its peak. Its Allan variance (IEEE Std 952-1997, Annex C, exponentially
correlated noise; El-Sheimy et al. 2008, with q_c = 2 sigma^2 / T):

    sigma_A^2(tau) = (2 sigma^2 T / tau) [1 - (T / (2 tau)) (3 - 4 e^{-tau/T} + e^{-2 tau/T})],

a rate random walk K^2 = 2 sigma^2 / T for tau << T, a white noise N^2 = 2 sigma^2 T for
tau >> T, with its peak 0.617 sigma at tau = 1.89 T.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import lfilter

from ..schema import nonnegative
from .base import (
    Coefficient,
    Effect,
    FitSpec,
    _g,
    parse_rho_tau,
    rho_tau_equivalents,
    tau_of,
)


class SensorBiasMarkov(Effect):
    id = "sensor.bias_markov"
    stage = "sensor"
    chain_order = 8
    draw_order = 4
    summary = "first-order Gauss-Markov sensor bias (exponentially correlated)"
    fit = FitSpec("noise", scale="std", shape=(("tau_s", 2.0, 1.0, "Ts|T", "log"),))
    # -- diagnosis hooks (base module docstring)
    channels = "output"
    drift = "sensor"

    @classmethod
    def explain(cls, params, Ts, ctx=None):
        tau = tau_of(params, Ts)
        one = (lambda v: v if v.size > 1 else v[0])
        # the Allan deviation of a first-order Gauss-Markov process peaks at 1.89 tau
        return (f"a flat excess below about {_g(one(1.0 / (2 * np.pi * tau)))} Hz that the plant does not "
                f"shape, and an Allan deviation bump near tau = {_g(one(1.89 * tau))} s: a Gauss-Markov bias "
                f"of std {_g(params['std'])} with correlation time {_g(one(tau))} s (exponentially correlated; IEEE 952's "
                f"bias instability B is the flicker floor, sensor.bias_instability)")

    @classmethod
    def equivalents(cls, params, Ts):
        return rho_tau_equivalents(params, Ts)

    def parse(self, t):
        self.params["std"] = t.vector("std", self.dims.p, check=nonnegative, expect="std >= 0")
        phi, tau = parse_rho_tau(t, self.dims.p, self.dims.Ts)
        self.params["rho" if t.has("rho") else "tau_s"] = phi if t.has("rho") else tau
        self.phi = phi
        self.c = np.sqrt(1.0 - phi**2) * self.params["std"]

    def coefficients(self):
        ident = (lambda v: np.asarray(v, float))
        return [Coefficient("sigma_GM", self.params["std"], "{u}", "std", ident),
                Coefficient("tau_GM", tau_of(self.params, self.dims.Ts), "s", "tau_s", ident)]

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
