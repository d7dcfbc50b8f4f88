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

IEEE Std 952 terms: the step ``q`` = Delta itself (output units), and, where the error is white
(the noise dithers it, above), the white-noise density it adds at the sample rate 1/Ts: its
variance Delta^2 / 12 per sample is that of a white noise of density

    N_q = Delta sqrt(Ts / 12),   sigma_A(tau) = N_q / sqrt(tau)  for tau = m Ts,

which adds to the sensor's own N in quadrature (what a calibration tool that knows only white
noise reads as N). IEEE 952's quantization coefficient Q (sigma_A(tau) = sqrt(3) Q / tau, IEEE Std
952-1997, Annex C; El-Sheimy et al. 2008) is of a quantized angle (an integrated output), not of
a quantized rate sample, and is not given.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...memo import Memo
from ..schema import positive
from .base import Coefficient, Effect, FitSpec, _g


class SensorQuantization(Effect):
    id = "sensor.quantization"
    stage = "sensor"
    chain_order = 12
    linear = False
    summary = "quantization of the measurement"
    fit = FitSpec("grid", scale="step")

    @classmethod
    def explain(cls, params, Ts, ctx=None):
        step = np.asarray(params["step"], float)
        return (f"every measured value lies on a grid of step {_g(params['step'])} (the chance of that "
                f"for a continuous signal is nil): the sensor is quantized, adding a variance of about "
                f"step^2/12 = {_g(step**2 / 12)} (white when the noise moves the signal by more than about half a step between samples)")

    def parse(self, t):
        self.params["step"] = t.vector("step", self.dims.p, check=positive, expect="steps > 0")

    def coefficients(self):
        rt = float(np.sqrt(self.dims.Ts / 12.0))
        step = self.params["step"]
        return [Coefficient("q", step, "{u}", "step", lambda v: np.asarray(v, float)),
                Coefficient("N_q", step * rt, "{u}/sqrt(Hz)", "step", lambda v: np.asarray(v, float) * rt, white=True)]

    def apply(self, y):
        d = self.params["step"]
        return d * np.rint(y / d)   # round half to even, as np.round and the seed

    def spectral(self):
        return [("white", self.params["step"] ** 2 / 12.0)]

    # -- prediction hooks (:mod:`.base`) ----------------------------------------------------------
    signal_dependent = True           # the uniform model's validity follows the signal's spread
    acts_after_sum = True             # Q(sum of every other term)

    def approximation_note(self, avg, others_var):
        """The uniform Delta^2/12 model's validity (:func:`uniform_model_error`) for the spread of the
        signal before the quantizer: the mean response's over the horizon and the other effects'."""
        spread = np.sqrt(avg.y_var + others_var)
        err = uniform_model_error(spread, self.params["step"])
        if not np.any(err > 0.01):
            return None
        return ("sensor.quantization: the signal spans few steps (std " + ", ".join(f"{s:.3g}" for s in spread)
                + " vs step " + ", ".join(f"{s:.3g}" for s in self.params["step"])
                + "): the uniform Delta^2/12 model may not hold")

    def error_acf(self, gamma, motion, cache=None, moments=None, cross=None):
        """:func:`quantization_acf` of this quantizer's step."""
        return quantization_acf(self.params["step"], gamma, motion, cache, moments, cross)

    def error_moments(self, mu, sigma2):
        """:func:`conditional_moments` of this quantizer's step."""
        return conditional_moments(self.params["step"], mu, sigma2)

    def moments_matter(self, sigma2):
        """:func:`mean_matters` of this quantizer's step (per output)."""
        step = np.broadcast_to(np.asarray(self.params["step"], float), np.shape(sigma2))
        return mean_matters(step, sigma2)


def uniform_model_error(sigma: np.ndarray, step: np.ndarray) -> np.ndarray:
    """Relative error bound of Delta^2/12 for a Gaussian input of std ``sigma`` (first term of
    the characteristic-function series, Widrow & Kollar 2008, ch. 5): 2 exp(-2 pi^2 sigma^2/Delta^2)
    times 12/pi^2 (the worst case over the mean)."""
    return (12.0 / np.pi**2) * np.exp(-2.0 * np.pi**2 * (np.asarray(sigma) / step) ** 2)


QUANT_MEAN_MIN = 1e-6      # exp(-2 pi^2 sigma^2 / Delta^2) below which the error's conditional mean is 0


def mean_matters(step, sigma2) -> np.ndarray:
    """Whether a Gaussian noise of variance ``sigma2`` before a quantizer of ``step`` leaves its
    error a conditional mean (its first Fourier factor at least :data:`QUANT_MEAN_MIN`: noise
    under about 0.84 step), elementwise."""
    return np.exp(-2.0 * np.pi**2 * np.asarray(sigma2, float) / np.asarray(step, float) ** 2) >= QUANT_MEAN_MIN


@dataclass
class Moments:
    """The quantizer's conditional moments over a record (:func:`conditional_moments`): y = Q(x),
    x_k = mu_k + n_k, n_k Gaussian of variance ``sigma2`` (its random part before the quantizer).
    ``g`` (n, p) = E[e_k] (e = Q(x) - x): the mean measurement is mu + g; ``var_e`` (p,) the mean
    over the record of Var(e_k); ``h`` (p,) the mean of E[e'(x_k)], by Stein's lemma the
    covariance of the error with the noise: Cov(n_j, e_k) = Cov(n_j, x_k) E[e'(x_k)]; ``active``
    (p,): outputs whose error depends on mu (the others: g = 0, h = 0, var_e = Delta^2 / 12).
    ``var_y`` (n, p): Var(y_k) at each sample (it follows where mu sits between the levels);
    ``k4`` (n, p): its excess fourth central moment, E[(y - E y)^4] - 3 Var(y)^2 (0 for a Gaussian;
    a few levels are far from it), for the spread of variance estimates."""

    g: np.ndarray
    var_e: np.ndarray
    h: np.ndarray
    active: np.ndarray
    sigma2: np.ndarray
    var_y: np.ndarray
    k4: np.ndarray


QUANT_TABLE = 4096         # phases per step of the moments' table (a stationary noise: g depends on mu mod Delta)
QUANT_TABLE_MIN = 0.03     # ... used for noise of at least this many steps (finer: the sums at every sample)


def _level_sums(D: float, m: np.ndarray, s: np.ndarray):
    """E[Q(m + n)] - m, Var(Q(m + n)), E[e'(m + n)] and the fourth central moment of Q(m + n) for
    n ~ N(0, s^2), by sums over the levels within 6 s of m (each decision level's CDF once)."""
    from scipy.special import ndtr

    K = int(np.ceil(6.0 * float(np.max(s)) / D)) + 1
    off = np.rint(m / D) * D - m                 # the nearest level relative to m: no cancellation
    m1, m2, m3, m4 = (np.zeros_like(m) for _ in range(4))
    dens = np.zeros_like(m)
    cdf_lo = ndtr((off - (K + 0.5) * D) / s)
    for k in range(-K, K + 1):
        lv = off + k * D
        upper = (lv + 0.5 * D) / s
        cdf_hi = ndtr(upper)
        pr = cdf_hi - cdf_lo
        cdf_lo = cdf_hi
        a = lv * pr
        m1 += a
        a = a * lv
        m2 += a
        a = a * lv
        m3 += a
        m4 += a * lv
        if k < K:
            dens += np.exp(-0.5 * upper * upper)
    var = np.maximum(m2 - m1 * m1, 0.0)
    # the fourth central moment, for the spread of variance estimates (the levels are few: not Gaussian)
    c4 = np.maximum(m4 - 4.0 * m3 * m1 + 6.0 * m2 * m1**2 - 3.0 * m1**4, 0.0)
    return m1, var, D * dens / (np.sqrt(2.0 * np.pi) * s) - 1.0, c4


def conditional_moments(step, mu: np.ndarray, sigma2: np.ndarray) -> Moments:
    """Exact moments of the quantized Gaussian by sums over the levels near mu_k (Widrow & Kollar
    2008, ch. 4-5): P(level j) = Phi((j + 1/2) Delta - mu)/s) - Phi(((j - 1/2) Delta - mu)/s).
    E[e'] = -1 + Delta sum_j phi_s((j + 1/2) Delta - mu) (e jumps by Delta at each decision level).
    ``mu`` (n, p); ``sigma2`` (n, p) or (p,) the variance of the random part at each sample. A
    sample whose exp(-2 pi^2 s^2 / Delta^2) is under :data:`QUANT_MEAN_MIN` (s > 0.84 Delta) has
    the uniform model's moments (its conditional mean is below 1e-6 Delta). With one variance over
    the record (no bias walk) the moments are periodic in mu with period Delta: they come from a
    table of :data:`QUANT_TABLE` phases (linear interpolation: off by < 3e-6 Delta for s >= 0.03
    Delta, where the sums take over), not from the sums at every sample."""
    mu = np.asarray(mu, float)
    n, p = mu.shape
    s2 = np.broadcast_to(np.asarray(sigma2, float), (n, p))
    step = np.broadcast_to(np.asarray(step, float), (p,))
    g = np.zeros((n, p))
    var_e = step**2 / 12.0
    h = np.zeros(p)
    active = np.zeros(p, bool)
    vy = s2 + step**2 / 12.0
    k4 = np.broadcast_to(-step**4 / 120.0, (n, p)).copy()     # a uniform's excess 4th moment, -Delta^4 / 120
    for j in range(p):
        D = float(step[j])
        live = mean_matters(D, s2[:, j])
        if not live.any():
            continue
        active[j] = True
        m = mu[live, j]
        s = np.maximum(np.sqrt(s2[live, j]), 1e-9 * D)
        if np.ptp(s) == 0 and s[0] >= QUANT_TABLE_MIN * D:
            ph = np.arange(QUANT_TABLE + 1) * (D / QUANT_TABLE)
            tab = _level_sums(D, ph, np.full(ph.size, s[0]))
            u = np.mod(m, D) * (QUANT_TABLE / D)             # the uniform grid's index and fraction
            i = np.minimum(u.astype(np.intp), QUANT_TABLE - 1)
            fr = u - i
            m1, var_y, hk, c4 = (t[i] + fr * (t[i + 1] - t[i]) for t in tab)
        else:
            m1, var_y, hk, c4 = _level_sums(D, m, s)
        g[live, j] = m1
        vy[live, j] = var_y
        k4[live, j] = c4 - 3.0 * var_y**2
        # Var(e) = Var(y) - s^2 (1 + 2 h): Var(x + e) = s^2 + 2 Cov(n, e) + Var(e)
        ve = var_y - s * s * (1.0 + 2.0 * hk)
        n_live = int(live.sum())
        var_e[j] = (float(np.sum(ve)) + (n - n_live) * D * D / 12.0) / n
        h[j] = float(np.sum(hk)) / n
    return Moments(g=g, var_e=np.asarray(var_e, float), h=h, active=active, sigma2=s2, var_y=vy, k4=k4)


QUANT_TERMS = 32           # Fourier terms of the error kept at most (the rest by the last term's factor)
QUANT_NEGLIGIBLE = 1e-9    # a term whose Gaussian factor is below this at every lag >= 1 is dropped
QUANT_WHITE = 1e-4         # ... and the error is white when the first term's factor is below this


def white_enough(step, gamma_min) -> bool:
    """Whether the quantizer's error is white to :data:`QUANT_WHITE` (its correlation at every lag
    >= 1 is below exp(-(2 pi / step)^2 gamma_min) for a variogram >= ``gamma_min`` there), for
    every output."""
    step = np.asarray(step, float)
    return bool(np.all(np.exp(-(2.0 * np.pi / step) ** 2 * np.asarray(gamma_min, float)) < QUANT_WHITE))


def _mean_factors(sigma2: np.ndarray, a2: float, m_max: int, samples: int = 4096) -> np.ndarray:
    """abar_m = mean_k exp(-a2 m^2 sigma2_k), m = 1..m_max (the conditional mean's m-th Fourier
    coefficient squared, relative, averaged over the record; over its distinct variances, on about
    ``samples`` (at most twice that) of its samples when they vary: a bias walk's growth)."""
    s2 = np.asarray(sigma2, float).ravel()
    s2, w = np.unique(s2[:: max(1, s2.size // samples)], return_counts=True)
    m = np.arange(1, m_max + 1)[:, None]
    return np.exp(-a2 * m * m * s2[None, :]) @ (w / w.sum())


def quantization_acf(step, gamma: np.ndarray, motion: np.ndarray | None = None,
                     cache: Memo | None = None, moments: Moments | None = None,
                     cross: np.ndarray | None = None) -> np.ndarray:
    """Autocovariance R_e(d), d = 0..L-1, of the quantization error (L, p) (formula in the module
    docstring). ``step`` (p,); ``gamma`` (L, p) the variogram E[(x_{k+d} - x_k)^2] / 2 of the random
    part of the signal before the quantizer (everything else in the model); ``motion`` (n, p) its
    deterministic part over the record (None: none). Lags d >= n of the motion have no pairs in the
    record and are set to 0 (no estimator uses them). ``cache``: a :class:`noiselab.memo.Memo` for
    the motion's factors C_m(d), keyed by output, term and step: one per motion, the caller's to
    keep apart (the diagnosis varies the noise, not the motion; its threads share it).

    ``moments`` (:func:`conditional_moments`): the error's conditional mean g is in the mean
    response, so what is left is the measurement's covariance about it, as a part added to the
    random part's own: Cov(e_k - g_k, e_{k+d} - g_{k+d}) + Cov(n, e) both ways. Lag 0 exactly,
    mean Var(e_k) + 2 h c(0); lags d >= 1: the Fourier form less the conditional mean's own
    terms, (Delta^2 / 2 pi^2) sum m^-2 (exp(-(2 pi m / Delta)^2 gamma(d)) - abar_m) C_m(d),
    abar_m = mean_k exp(-(2 pi m / Delta)^2 s_k^2), scaled to the exact lag 0 (the Fourier form
    assumes mu spread evenly over the steps: a sine over 4 steps overstated Var(e) by 40 %),
    plus 2 h c(d) (Stein's lemma, exact; ``cross`` (L, p) = c(d), the autocovariance of the
    stationary random part before the quantizer). h is about 0 when mu is spread evenly; it
    is -1 where mu sits on a level and the noise cannot reach a threshold (the quantizer holds the
    measurement: the part, negative then, cancels the noise's own). Per output: a noise shared by
    two outputs gets no cross-output term."""
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
        mo = moments is not None and bool(moments.active[j])
        if mo:
            cj = np.zeros(L) if cross is None else np.asarray(cross, float)[:L, j]
            hterm = 2.0 * float(moments.h[j]) * cj
        if L == 1 or white_enough(D, g_min):
            if mo:
                R[:, j] = hterm
                R[0, j] += float(moments.var_e[j])
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
        abar = _mean_factors(moments.sigma2[:, j], a2, m_max) if mo else None
        for m in range(1, m_max + 1):
            f = np.exp(-a2 * m * m * g)
            if mo:
                f = f - abar[m - 1]
            if x is not None:
                key = (j, m, D)
                c = None if cache is None else cache.get(key)
                if c is None or c.size < min(L, n):    # the lags asked for (a longer call recomputes)
                    z = np.exp(1j * (2.0 * np.pi * m / D) * x)
                    Z = np.fft.fft(z, nfft)
                    c = (np.fft.ifft(Z * np.conj(Z))[:n].real / (n - np.arange(n)))[:min(L, n)].copy()
                    if cache is not None:
                        cache.put(key, c)
                C = np.zeros(L)
                C[: min(L, n)] = c[:L]
                f = f * C
            last = f
            acc += f / (m * m)
        tail = np.pi**2 / 6.0 - np.sum(1.0 / np.arange(1, m_max + 1) ** 2)
        acc += tail * last
        R[1:, j] = D * D / (2.0 * np.pi**2) * acc[1:]
        if mo:
            # the Fourier form's own lag 0, sum over every m of (1 - abar_m) / m^2 (to 4096 terms)
            big = 4096
            r0 = np.pi**2 / 6.0 - float(np.sum(_mean_factors(moments.sigma2[:, j], a2, big, samples=256)
                                                / np.arange(1, big + 1) ** 2))
            r0 *= D * D / (2.0 * np.pi**2)
            ve = float(moments.var_e[j])
            R[1:, j] *= ve / r0 if r0 > 0 else 0.0
            R[0, j] = ve
            R[:, j] += hterm
    return R
