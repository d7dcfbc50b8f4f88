"""``sensor.white``: white measurement noise v_k ~ N(0, std^2) (seed: sigma_v)."""

from __future__ import annotations

from ..schema import nonnegative
from .base import Effect, FitSpec, _g


class SensorWhite(Effect):
    id = "sensor.white"
    stage = "sensor"
    chain_order = 9
    draw_order = 5
    summary = "white sensor noise"
    fit = FitSpec("noise", scale="std")

    @classmethod
    def explain(cls, params, Ts, ctx=None):
        return (f"a flat floor above the model's at high frequency, the same in every time window: "
                f"white sensor noise of std {_g(params['std'])}")

    def parse(self, t):
        self.params["std"] = t.vector("std", self.dims.p, check=nonnegative, expect="std >= 0")

    def n_normals(self):
        return self.dims.p

    def sensor_terms(self, e, state):
        return self.params["std"] * e

    def spectral(self):
        return [("white", self.params["std"] ** 2)]
