"""``sensor.integral_white``: white noise on the integral of the output, IEEE Std 952's quantization
noise Q (angle quantization for a rate gyro, velocity quantization for an accelerometer) and, for an
oscillator's fractional frequency, white phase noise.

The process: the integral of the output (angle, velocity, phase) read with a white error q_k of
standard deviation Q (output units times s), and the output the integral's difference over a
sample,

    v_k = (q_k - q_{k-1}) / Ts,                       q_k ~ N(0, Q^2) independent,

so v is a first-order moving average with coefficient -1: variance 2 Q^2 / Ts^2, lag-1
autocorrelation -1/2, zero beyond. Its one-sided PSD rises toward Nyquist,

    S(f) = 2 Ts (Q / Ts)^2 |1 - exp(-i 2 pi f Ts)|^2 = (8 Q^2 / Ts) sin^2(pi f Ts)
         ~ 2 (2 pi f)^2 Q^2 Ts                        for f << 1/Ts,

twice IEEE 952's two-sided S(f) = Ts Q^2 (2 pi f)^2 (IEEE Std 952-1997 Annex C, "quantization
noise"; this package's PSDs are one-sided, :mod:`noiselab.model.spectra`). Averages over m samples
telescope, (q_{k+m} - q_k) / (m Ts), so the Allan variance is exactly

    sigma_A^2(tau) = 3 Q^2 / tau^2,                   tau = m Ts, every m >= 1,

the -1 slope of IEEE 952's table C.1 (sigma_A(tau) = sqrt(3) Q / tau), which NIST SP 1065 (table 5)
calls white phase modulation (alpha = 2) for frequency data.

Realisation and prediction share two states per output, s1_k = (Q/Ts) q_{k-1} and s2_k = (Q/Ts)
q_{k-2}, v_k = s1_k - s2_k (a one-sample delay of the definition, the same stationary process);
they start stationary (the record's first sample already differences two readings), so
:meth:`initial_cov` is (Q/Ts)^2 I for the covariance recursion.
"""

from __future__ import annotations

import numpy as np

from ..schema import nonnegative
from .base import Coefficient, Effect, FitSpec, _g


class SensorIntegralWhite(Effect):
    id = "sensor.integral_white"
    stage = "sensor"
    chain_order = 9.5          # a noise of the reading: before the output filter and the quantizer
    draw_order = 8             # after every other source: a model without it draws as before
    summary = "white noise on the output's integral (quantization noise Q, white phase noise)"
    # the diagnosis fits Q alone (a noise of fixed shape scaled by Q^2), one per output
    fit = FitSpec("noise", scale="Q")
    channels = "output"

    @classmethod
    def explain(cls, params, Ts, ctx=None):
        Q = np.atleast_1d(np.asarray(params["Q"], float))
        one = (lambda v: v if v.size > 1 else v[0])
        return (f"a PSD rising as f^2 toward Nyquist, an Allan deviation falling as 1/tau "
                f"(sqrt(3) Q / tau = {_g(one(np.sqrt(3.0) * Q))} at tau = 1 s) and a lag-1 autocorrelation "
                f"toward -1/2: white noise on the output's integral (IEEE 952 quantization noise, "
                f"white phase noise) of Q = {_g(one(Q))}")

    def parse(self, t):
        self.params["Q"] = t.vector("Q", self.dims.p, check=nonnegative,
                                    expect="Q >= 0 in output units times s")

    def coefficients(self):
        return [Coefficient("Q", self.params["Q"], "({u})*s", "Q", lambda v: np.asarray(v, float))]

    def _c(self) -> np.ndarray:
        return np.broadcast_to(np.asarray(self.params["Q"], float) / self.dims.Ts, (self.dims.p,))

    def n_normals(self):
        return self.dims.p

    def init_state(self, static_rng, trials):
        # stationary start: the readings q_{-1}, q_{-2} before the record, from the static randoms
        return {"q": static_rng.standard_normal((trials, 2, self.dims.p))}   # q_{k-2}, q_{k-1}

    def initial_cov(self):
        """Covariance of (s1, s2) at k = 0: stationary, (Q/Ts)^2 I."""
        c = self._c()
        return np.diag(np.concatenate([c, c]) ** 2)

    def sensor_terms(self, e, state):
        ext = np.concatenate([state["q"], e], axis=1)              # q_{-2}, q_{-1}, q_0, ...
        n = e.shape[1]
        state["q"] = ext[:, n:n + 2].copy()
        return self._c() * (ext[:, 1:n + 1] - ext[:, :n])          # (Q/Ts)(q_{k-1} - q_{k-2})

    def sensor_linear(self):
        p, c = self.dims.p, self._c()
        F = np.zeros((2 * p, 2 * p))
        F[p:, :p] = np.eye(p)                                      # s2_{k+1} = s1_k
        G = np.vstack([np.diag(c), np.zeros((p, p))])              # s1_{k+1} = (Q/Ts) q_k
        H = np.hstack([np.eye(p), -np.eye(p)])
        return F, G, H
