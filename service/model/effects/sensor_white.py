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
        band = (ctx or {}).get("band")
        where = f"above {_g(band[0])} Hz" if band else "at high frequency"
        return (f"a flat floor {where} that the plant does not shape, the same in every time window: "
                f"white sensor noise of std {_g(params['std'])}")

    def parse(self, t):
        self.params["std"] = t.vector("std", self.dims.p, check=nonnegative, expect="std >= 0")

    def n_normals(self):
        return self.dims.p

    def sensor_terms(self, e, state):
        return self.params["std"] * e

    def spectral(self):
        return [("white", self.params["std"] ** 2)]
