"""``actuator.lag``: first-order actuator dynamics tau_s l' = -l + drive, the plant sees l.

The lag states are appended to the continuous plant and discretized with it (exact under zoh), so
they are part of the plant state x = [plant states, lag states]. A plant D term acts on l.
"""

from __future__ import annotations

import numpy as np

from ..schema import positive
from .base import Effect, FitSpec, _g


class ActuatorLag(Effect):
    id = "actuator.lag"
    stage = "actuator"
    role = "modifier"
    chain_order = 3
    summary = "first-order actuator lag between command and plant input"
    fit = FitSpec("mean", shape=(("tau_s", 0.2, 0.05, "Ts|T", "log"),), needs_command=True)
    # -- diagnosis hooks (base module docstring)
    # one time constant over the inputs only (not per_channel_mean): per-input time constants can
    # take up the amplitude loss of a saturation beside it (two lags and a Gauss-Markov bias fitted
    # in place of one lag and a limit, on a two-input plant)

    @classmethod
    def explain(cls, params, Ts, ctx=None):
        fc = 1.0 / (2 * np.pi * np.mean(params["tau_s"]))
        return (f"the response lags the predicted one and loses amplitude towards {_g(fc)} Hz: first-order "
                f"actuator dynamics with time constant {_g(params['tau_s'])} s")

    def parse(self, t):
        self.params["tau_s"] = t.vector("tau_s", self.dims.m, check=positive, expect="time constants in s > 0")

    def augment(self, A, B, C, D, L):
        n, m = B.shape
        inv = np.diag(1.0 / self.params["tau_s"])
        A2 = np.block([[A, B], [np.zeros((m, n)), -inv]])
        B2 = np.vstack([np.zeros((n, m)), inv])
        C2 = np.hstack([C, D])
        D2 = np.zeros_like(D)
        L2 = np.vstack([L, np.zeros((m, L.shape[1]))])
        return A2, B2, C2, D2, L2
