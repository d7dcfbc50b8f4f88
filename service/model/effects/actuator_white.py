"""``actuator.white``: white noise added to the command in the input channel, n_k ~ N(0, std^2)."""

from __future__ import annotations

import numpy as np

from ..schema import nonnegative
from .base import Effect, FitSpec, _g, band_phrase


class ActuatorWhite(Effect):
    id = "actuator.white"
    stage = "actuator"
    chain_order = 1
    draw_order = 0
    summary = "white actuator noise in the input channel"
    fit = FitSpec("noise", scale="std")
    # -- diagnosis hooks (base module docstring)
    channels = "input"

    @classmethod
    def explain(cls, params, Ts, ctx=None):
        return (f"{band_phrase(ctx)}excess power with the shape of the plant's response to its command "
                f"input: white actuator noise of std {_g(params['std'])}")

    def parse(self, t):
        self.params["std"] = t.vector("std", self.dims.m, check=nonnegative, expect="std >= 0")

    def n_normals(self):
        return self.dims.m

    def actuator_terms(self, e, state):
        """Noise added to the drive for a block of normals e (trials, n, m)."""
        return self.params["std"] * e

    def drive_linear(self):
        m = self.dims.m
        return np.zeros((0, 0)), np.zeros((0, m)), np.zeros((m, 0)), np.diag(self.params["std"])
