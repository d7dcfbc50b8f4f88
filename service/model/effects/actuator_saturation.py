"""``actuator.saturation``: the drive is clipped to [-limit, limit].

Predictions linearize around the operating point (seed section 7, statistical linearization):
for a Gaussian drive u ~ N(mu_k, s_k^2) the mean input is E[sat(u)] and the noise passes with the
effective gain g_k = E[sat'(u)] = P(|u| < limit) (Bussgang), so its covariance scales by g_k^2.
Exact when the drive never reaches the limit; approximate (no harmonics) when it does.
"""

from __future__ import annotations

import numpy as np

from ..schema import positive
from .base import Effect, FitSpec, _g


class ActuatorSaturation(Effect):
    id = "actuator.saturation"
    stage = "actuator"
    role = "modifier"
    chain_order = 4
    linear = False
    summary = "actuator saturation of the plant input"
    fit = FitSpec("mean", shape=(("limit", 0.02, 1.2, "umax", "log"),), needs_command=True)
    # -- diagnosis hooks (base module docstring)
    per_channel_mean = True
    clips = True

    @classmethod
    def explain(cls, params, Ts, ctx=None):
        return (f"the response falls short of the predicted one where the command is large (the drive is "
                f"clipped), with odd harmonics of the command in the residual: the actuator saturates at "
                f"about {_g(params['limit'])}")

    def parse(self, t):
        self.params["limit"] = t.vector("limit", self.dims.m, check=positive, expect="limits > 0")

    def apply(self, u):
        lim = self.params["limit"]
        return np.minimum(np.maximum(u, -lim), lim)

    def knots(self):
        lim = self.params["limit"]
        return [np.array([-l, l]) for l in lim]
