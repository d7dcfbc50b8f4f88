"""``sensor.quantization``: y rounded to the nearest multiple of ``step`` (seed section 6.1).

Simulation: Delta * round(y / Delta) (round half to even, as numpy and the seed). Prediction: the
uniform model, an additive white error of variance Delta^2 / 12, independent of the signal. It holds
when the signal before the quantizer spans many steps and is not locked to the grid (Widrow: with
Gaussian input of std sigma the error of the variance is ~ exp(-2 pi^2 sigma^2 / Delta^2)); it fails
for slow or periodic signals locked to the grid, where the error is signal dependent.
:func:`uniform_model_error` gives the Widrow bound used by the predictor's validity note.
"""

from __future__ import annotations

import numpy as np

from ..schema import positive
from .base import Effect, FitSpec, _g


class SensorQuantization(Effect):
    id = "sensor.quantization"
    stage = "sensor"
    chain_order = 12
    linear = False
    summary = "quantization of the measurement"
    fit = FitSpec("grid")

    @classmethod
    def explain(cls, params, Ts, ctx=None):
        return (f"every measured value lies on a grid of step {_g(params['step'])} (the chance of that "
                f"for a continuous signal is nil): the sensor is quantized, adding step^2/12 of white noise")

    def parse(self, t):
        self.params["step"] = t.vector("step", self.dims.p, check=positive, expect="steps > 0")

    def apply(self, y):
        d = self.params["step"]
        return d * np.rint(y / d)   # round half to even, as np.round and the seed

    def spectral(self):
        return [("white", self.params["step"] ** 2 / 12.0)]


def uniform_model_error(sigma: np.ndarray, step: np.ndarray) -> np.ndarray:
    """Relative error bound of Delta^2/12 for a Gaussian input of std ``sigma`` (first term of
    the characteristic-function series, Widrow & Kollar 2008, ch. 5): 2 exp(-2 pi^2 sigma^2/Delta^2)
    times 12/pi^2 (the worst case over the mean)."""
    return (12.0 / np.pi**2) * np.exp(-2.0 * np.pi**2 * (np.asarray(sigma) / step) ** 2)
