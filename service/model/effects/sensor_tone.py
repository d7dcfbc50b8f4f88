"""``sensor.tone``: periodic interference amplitude sin(2 pi f t_k + phi) (mains hum, vibration).

The phase phi is random (uniform, one per output, drawn once per run), so the tone is a stationary
process: variance amplitude^2 / 2, autocovariance (amplitude^2/2) cos(2 pi f tau), a line at f.
"""

from __future__ import annotations

import numpy as np

from ..schema import nonnegative
from .base import Effect, FitSpec, _g


class SensorTone(Effect):
    id = "sensor.tone"
    stage = "sensor"
    chain_order = 10
    summary = "periodic interference (a tone)"
    fit = FitSpec("line", scale="amplitude")

    @classmethod
    def explain(cls, params, Ts, ctx=None):
        return (f"a narrow spectral line at {_g(params['frequency_hz'])} Hz that no noise source explains: "
                f"periodic interference (a tone) of amplitude {_g(params['amplitude'])}")

    def parse(self, t):
        self.params["amplitude"] = t.vector("amplitude", self.dims.p, check=nonnegative, expect="amplitudes >= 0")
        nyq = 0.5 / self.dims.Ts
        self.params["frequency_hz"] = t.vector(
            "frequency_hz", self.dims.p, check=lambda v: bool(np.all((v > 0) & (v < nyq))),
            expect=f"frequencies in Hz between 0 and the Nyquist frequency {nyq:g}")

    def init_state(self, static_rng, trials):
        return {"phase": static_rng.uniform(0.0, 2.0 * np.pi, (trials, self.dims.p)), "k": 0}

    def _tone(self, k0, n, state):
        t = np.arange(k0, k0 + n, dtype=np.float64) * self.dims.Ts
        arg = 2.0 * np.pi * t[None, :, None] * self.params["frequency_hz"] + state["phase"][:, None, :]
        return self.params["amplitude"] * np.sin(arg)

    def sensor_terms(self, e, state, n):
        out = self._tone(state["k"], n, state)
        state["k"] += n
        return out

    def spectral(self):
        return [("tone", self.params["amplitude"], self.params["frequency_hz"])]
