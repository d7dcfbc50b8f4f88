"""``sensor.quantization``: y rounded to the nearest multiple of ``step`` (seed section 6.1).

Simulation: Delta * round(y / Delta) (round half to even, as numpy and the seed). Prediction: an
additive error of variance Delta^2 / 12, uncorrelated with the signal (the uniform model). It holds
when the signal before the quantizer spans many steps and is not locked to the grid (Widrow: with
Gaussian input of std sigma the error of the variance is ~ exp(-2 pi^2 sigma^2 / Delta^2)); it fails
for slow or periodic signals locked to the grid, where the error is signal dependent.
:func:`uniform_model_error` gives the Widrow bound used by the predictor's validity note.

The error is white only when the signal moves by more than a step between samples (or a dither of
std above ~0.4 Delta, the sensor's own white noise, decorrelates it). A coarse step on a slow signal
(an encoder, an undithered ADC) gives a correlated error: a sawtooth while the signal crosses the
steps. Its autocovariance follows from the error's Fourier series e(x) = sum_{m != 0} c_m
e^{i 2 pi m x / Delta}, |c_m|^2 = Delta^2 / (4 pi^2 m^2), and the Gaussian characteristic function
of the increment x_{k+d} - x_k (Widrow & Kollar 2008, ch. 9, the terms that survive when the signal
spans many steps): with gamma(d) the variogram of the random part of the signal before the quantizer
and mu_k its deterministic part (the mean response, the tones),

    R_e(d) = (Delta^2 / (2 pi^2)) sum_{m >= 1} m^-2 exp(-(2 pi m / Delta)^2 gamma(d)) C_m(d),
    C_m(d) = mean_k cos(2 pi m (mu_{k+d} - mu_k) / Delta)      (over the record),

R_e(0) = Delta^2 / 12 (:func:`quantization_acf`). With a white dither of variance s^2, gamma(d >= 1)
>= s^2, and the correlation left is below exp(-4 pi^2 s^2 / Delta^2): 0.2 at s = 0.2 Delta, 2e-3
at s = 0.4 Delta.
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


QUANT_TERMS = 32           # Fourier terms of the error kept at most (the rest by the last term's factor)
QUANT_NEGLIGIBLE = 1e-9    # a term whose Gaussian factor is below this at every lag >= 1 is dropped
QUANT_WHITE = 1e-4         # ... and the error is white when the first term's factor is below this


def white_enough(step, gamma_min) -> bool:
    """Whether the quantizer's error is white to :data:`QUANT_WHITE` (its correlation at every lag
    >= 1 is below exp(-(2 pi / step)^2 gamma_min) for a variogram >= ``gamma_min`` there), for
    every output."""
    step = np.asarray(step, float)
    return bool(np.all(np.exp(-(2.0 * np.pi / step) ** 2 * np.asarray(gamma_min, float)) < QUANT_WHITE))


def quantization_acf(step, gamma: np.ndarray, motion: np.ndarray | None = None,
                     cache: dict | None = None) -> np.ndarray:
    """Autocovariance R_e(d), d = 0..L-1, of the quantization error (L, p) (formula in the module
    docstring). ``step`` (p,); ``gamma`` (L, p) the variogram E[(x_{k+d} - x_k)^2] / 2 of the random
    part of the signal before the quantizer (everything else in the model); ``motion`` (n, p) its
    deterministic part over the record (None: none). Lags d >= n of the motion have no pairs in the
    record and are set to 0 (no estimator uses them). ``cache``: a dict for the motion's factors
    C_m(d), keyed by output, term and step: one dict per motion, the caller's to keep apart (the
    diagnosis varies the noise, not the motion)."""
    gamma = np.asarray(gamma, float)
    L, p = gamma.shape
    step = np.broadcast_to(np.asarray(step, float), (p,))
    R = np.zeros((L, p))
    if L == 0:
        return R
    for j in range(p):
        D = float(step[j])
        a2 = (2.0 * np.pi / D) ** 2
        g = np.maximum(gamma[:, j], 0.0)
        g_min = float(np.min(g[1:])) if L > 1 else 0.0
        R[0, j] = D * D / 12.0
        if L == 1 or white_enough(D, g_min):
            continue
        # terms m with exp(-a2 m^2 g_min) above QUANT_NEGLIGIBLE somewhere
        m_max = QUANT_TERMS if g_min <= 0 else \
            int(min(QUANT_TERMS, max(1, np.ceil(np.sqrt(-np.log(QUANT_NEGLIGIBLE) / (a2 * g_min))))))
        x = None if motion is None else np.asarray(motion, float)[:, j]
        if x is not None and np.ptp(x) == 0:
            x = None
        n = None if x is None else x.size
        if x is not None:
            nfft = 1 << int(np.ceil(np.log2(2 * n)))
        acc = np.zeros(L)
        last = np.zeros(L)
        for m in range(1, m_max + 1):
            f = np.exp(-a2 * m * m * g)
            if x is not None:
                key = (j, m, D)
                c = None if cache is None else cache.get(key)
                if c is None or c.size < min(L, n):    # the lags asked for (a longer call recomputes)
                    z = np.exp(1j * (2.0 * np.pi * m / D) * x)
                    Z = np.fft.fft(z, nfft)
                    c = (np.fft.ifft(Z * np.conj(Z))[:n].real / (n - np.arange(n)))[:min(L, n)].copy()
                    if cache is not None:
                        cache[key] = c
                C = np.zeros(L)
                C[: min(L, n)] = c[:L]
                f = f * C
            last = f
            acc += f / (m * m)
        tail = np.pi**2 / 6.0 - np.sum(1.0 / np.arange(1, m_max + 1) ** 2)
        acc += tail * last
        R[1:, j] = D * D / (2.0 * np.pi**2) * acc[1:]
    return R
