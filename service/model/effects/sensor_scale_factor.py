"""``sensor.scale_factor``: y = (1 + error) (C x + D u) + ...: a gain error of the sensor.

It scales the plant's contribution to y (its mean response and its noise), not the sensor's own
additive noises, and the derivative used by the jitter effect.
"""

from __future__ import annotations

import numpy as np

from .base import Effect, FitSpec, _g


class SensorScaleFactor(Effect):
    id = "sensor.scale_factor"
    stage = "sensor"
    role = "modifier"
    chain_order = 6
    summary = "sensor scale-factor error"
    fit = FitSpec("mean", shape=(("error", -0.5, 1.0, "1", "lin"),), needs_command=True)
    # -- diagnosis hooks (base module docstring)
    per_channel_mean = True
    gain_start = True

    @classmethod
    def explain(cls, params, Ts, ctx=None):
        return (f"the residual is a copy of the predicted response itself (in phase, at the command's "
                f"frequencies): a sensor scale-factor error of {_g(np.asarray(params['error']) * 100)} %")

    def parse(self, t):
        self.params["error"] = t.vector("error", self.dims.p, check=lambda v: bool(np.all(v > -1)),
                                        expect="errors > -1 (relative, e.g. 0.02 for +2 %)")

    def output_gain(self):
        return 1.0 + self.params["error"]
