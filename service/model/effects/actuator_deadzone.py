"""``actuator.deadzone``: a drive inside [-width, width] has no effect; outside, u - sign(u) width.

Predictions use the same statistical linearization as the saturation: mean E[dz(u)], gain
g_k = P(|u| > width) for a Gaussian drive (seed section 7).
"""

from __future__ import annotations

import numpy as np

from ..schema import positive
from .base import Effect, FitSpec, _g


class ActuatorDeadzone(Effect):
    id = "actuator.deadzone"
    stage = "actuator"
    role = "modifier"
    chain_order = 5
    linear = False
    summary = "actuator dead zone"
    fit = FitSpec("mean", shape=(("width", 0.003, 0.9, "umax", "log"),), needs_command=True)
    # -- diagnosis hooks (base module docstring)
    per_channel_mean = True
    clips = True

    @classmethod
    def explain(cls, params, Ts, ctx=None):
        return (f"small commands have no effect and the response is pulled in at every zero crossing "
                f"(odd harmonics of the command in the residual): an actuator dead zone of about "
                f"{_g(params['width'])}")

    def parse(self, t):
        self.params["width"] = t.vector("width", self.dims.m, check=positive, expect="widths > 0")

    def apply(self, u):
        w = self.params["width"]
        return np.sign(u) * np.maximum(np.abs(u) - w, 0.0)

    def knots(self):
        return [np.array([-w, w]) for w in self.params["width"]]
