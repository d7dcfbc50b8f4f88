"""``sensor.bias_instability``: a flicker (1/f) bias, IEEE Std 952's bias instability B.

The process (IEEE Std 952-1997, Annex C, "bias instability"): a bias whose rate PSD is

    S(f) = B^2 / (2 pi f)                          two-sided, as IEEE 952 writes its PSDs
                                                   (Annex C: sigma^2(tau) = 4 int_0^inf S(f)
                                                   sin^4(pi f tau) / (pi f tau)^2 df)

between the band's edges f_lo and f_hi, in the output's units per sqrt(Hz). This package's PSDs
are one-sided (:mod:`noiselab.model.spectra`), so the predictor's PSD of it is 2 S(f) = B^2 / (pi f).
Its Allan variance is then flat: sigma_A^2 = 4 int S(f) sin^4(x)/x^2 df = (2 B^2 / pi) int_0^inf
sin^4(x)/x^3 dx = (2 ln 2 / pi) B^2, so sigma_A = sqrt(2 ln 2 / pi) B ~ 0.664 B for
1/f_hi << tau << 1/f_lo (IEEE 952 table C.1; El-Sheimy et al. 2008, table 1).

Realisation (and prediction: the same sum). 1/f noise is a superposition of first-order
Gauss-Markov processes with log-uniformly distributed correlation times (Keshner 1982, Proc. IEEE
70(3); the "sum of first-order Markov processes" of the INS literature). A Gauss-Markov process of
variance s^2 and correlation time T has the two-sided PSD 2 s^2 T / (1 + (2 pi f T)^2); with a
variance density c per unit of ln T,

    int 2 c / (1 + (2 pi f T)^2) dT = c / (2 f),        so c = B^2 / pi gives B^2 / (2 pi f).

The integral over ln T is taken as a sum over K correlation times T_i, log-spaced with
:data:`PER_DECADE` per decade, each of variance s_i^2 = (B^2 / pi) ln(T_{i+1} / T_i). They span
[1 / (2 pi f_hi) / 10^HI_MARGIN, 10^LO_MARGIN / (2 pi f_lo)]: the sum's own roll-off at each end
lies outside the band. Each is simulated exactly at the sample times,
b_{i,k+1} = phi_i b_{i,k} + s_i sqrt(1 - phi_i^2) xi_{i,k}, phi_i = exp(-Ts / T_i), and the bias is
sum_i b_{i,k}. The predictor sees the same states through :meth:`sensor_linear` (F = diag(phi),
G = diag(s sqrt(1 - phi^2)), H sums each output's K states), so its variance, ACF, PSD and Allan
variance are exact for the sum as realised, aliasing included.

Accuracy of the sum against the exact 1/f PSD: with f_hi <= 1/(10 Ts) (the largest allowed), the
one-sided PSD of the sampled sum is within :data:`ACCURACY_DB` (0.25 dB) of B^2 / (pi f) over
[f_lo, f_hi] (the ripple between the T_i is below 0.05 dB; the rest is each end's roll-off and, at
f_hi, aliasing). Its Allan deviation is within 3 % of 0.664 B from about tau = 3 / f_hi to
1 / (10 f_lo) (tested).

Defaults: f_hi = 1/(10 Ts) (a decade of the spectrum, up to a fifth of Nyquist, where a sensor's
white noise normally dominates a flicker anyway), f_lo = 1/(1e6 Ts) (a record of a million samples:
2.8 h at 100 Hz). A record much longer than 1/f_lo sees the floor turn into the white-noise
descent beyond it; give ``f_lo_hz`` for it.

Starting state: the sum starts in its stationary distribution (each b_{i,0} ~ N(0, s_i^2), drawn
from the run's static randoms): a sensor's flicker is there before the record starts, and a
correlation time of 1/f_lo is longer than most records, so a start at zero would leave the slow
states far from the steady state the predictions describe.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import lfilter

from ..schema import nonnegative
from .base import Coefficient, Effect, FitSpec, _g

PER_DECADE = 3            # correlation times per decade of the sum
LO_MARGIN = 1.0           # decades of correlation times beyond 1 / (2 pi f_lo)
HI_MARGIN = 0.5           # decades of correlation times below 1 / (2 pi f_hi)
ACCURACY_DB = 0.25        # |10 log10(S_sum / S_1/f)| over [f_lo, f_hi] (module docstring)
FLOOR = float(np.sqrt(2.0 * np.log(2.0) / np.pi))   # sigma_A / B on the flicker floor, 0.6643
F_HI_TS = 0.1             # default and largest f_hi, in 1/Ts
F_LO_TS = 1e-6            # default f_lo, in 1/Ts


def correlation_times(f_lo: float, f_hi: float) -> np.ndarray:
    """The sum's correlation times T_i (s): log-spaced, :data:`PER_DECADE` per decade, over
    [1 / (2 pi f_hi) / 10^HI_MARGIN, 10^LO_MARGIN / (2 pi f_lo)]."""
    t_min = 1.0 / (2 * np.pi * f_hi) / 10**HI_MARGIN
    t_max = 10**LO_MARGIN / (2 * np.pi * f_lo)
    k = int(np.ceil(np.log10(t_max / t_min) * PER_DECADE)) + 1
    return np.geomspace(t_min, t_max, k)


def flicker_psd(B, f) -> np.ndarray:
    """The exact flicker PSD, one-sided as this package's: 2 B^2 / (2 pi f) (units^2/Hz), (len(f), p)."""
    return np.asarray(B, float)[None, :] ** 2 / (np.pi * np.asarray(f, float)[:, None])


class SensorBiasInstability(Effect):
    id = "sensor.bias_instability"
    stage = "sensor"
    chain_order = 8.5          # beside the other biases: added before the white noise and the quantizer
    draw_order = 7             # after every existing source: a model without it draws as before
    summary = "flicker (1/f) sensor bias (bias instability B)"
    # the diagnosis fits B alone: its variance is B^2 times a fixed shape (the sum's PSD over the
    # default band); one B per output, and a slow sensor drift, as the walk and the Gauss-Markov bias
    fit = FitSpec("noise", scale="B")
    channels = "output"
    drift = "sensor"

    @classmethod
    def explain(cls, params, Ts, ctx=None):
        B = np.atleast_1d(np.asarray(params["B"], float))
        one = (lambda v: v if v.size > 1 else v[0])
        f_lo, f_hi = params.get("f_lo_hz", F_LO_TS / Ts), params.get("f_hi_hz", F_HI_TS / Ts)
        return (f"a PSD falling as 1/f and a flat Allan deviation floor of {_g(one(FLOOR * B))} between "
                f"averaging times of about {_g(3.0 / f_hi)} and {_g(0.1 / f_lo)} s: a flicker bias "
                f"(bias instability) of B = {_g(one(B))}")

    def parse(self, t):
        Ts = self.dims.Ts
        self.params["B"] = t.vector("B", self.dims.p, check=nonnegative, expect="B >= 0 in output units")
        f_hi = t.number("f_hi_hz", None, check=lambda v: 0 < v <= F_HI_TS / Ts,
                        expect=f"a frequency in Hz > 0 and at most 1/(10 Ts) = {F_HI_TS / Ts:g}")
        f_lo = t.number("f_lo_hz", None, check=lambda v: v > 0, expect="a frequency in Hz > 0")
        if f_hi is not None:
            self.params["f_hi_hz"] = f_hi
        if f_lo is not None:
            self.params["f_lo_hz"] = f_lo
        self.f_hi = F_HI_TS / Ts if f_hi is None else f_hi
        self.f_lo = F_LO_TS / Ts if f_lo is None else f_lo
        if not self.f_lo < self.f_hi / 10:
            raise t.error("f_lo_hz", f"expected f_lo_hz at most f_hi_hz / 10 = {self.f_hi / 10:g} (a decade of "
                                     f"flicker at least), got f_lo_hz = {self.f_lo:g}")
        if self.f_hi / self.f_lo > 1e12:
            raise t.error("f_lo_hz", f"expected at most 12 decades between f_lo_hz and f_hi_hz, got "
                                     f"{self.f_lo:g} to {self.f_hi:g} Hz")
        self.taus = correlation_times(self.f_lo, self.f_hi)
        # per unit of ln T: variance B^2 / pi (module docstring); every T_i the same step in ln T
        step = np.log(self.taus[1] / self.taus[0])
        self.s = np.sqrt(step / np.pi) * self.params["B"][:, None] * np.ones(self.taus.size)   # (p, K)
        self.phi = np.exp(-Ts / self.taus)                                                     # (K,)
        self.c = self.s * np.sqrt(1.0 - self.phi**2)                                           # (p, K)

    def coefficients(self):
        return [Coefficient("B", self.params["B"], "{u}", "B", lambda v: np.asarray(v, float))]

    @property
    def K(self) -> int:
        return self.taus.size

    def n_normals(self):
        return self.dims.p * self.K

    def init_state(self, static_rng, trials):
        # stationary start (module docstring): b_{i,0} ~ N(0, s_i^2)
        return {"b": self.s[None] * static_rng.standard_normal((trials, self.dims.p, self.K))}

    def initial_cov(self):
        """Covariance of the states at k = 0 (the stationary start), for the covariance recursion."""
        return np.diag((self.s**2).reshape(-1))

    def sensor_terms(self, e, state):
        # normals (trials, n, p K), output j's K processes side by side; b_k (before its update
        # with xi_k) enters y_k, as the Gauss-Markov bias
        trials, n = e.shape[0], e.shape[1]
        out = np.zeros((trials, n, self.dims.p))
        b = state["b"]
        for j in range(self.dims.p):
            for i in range(self.K):
                x = e[:, :, j * self.K + i]
                nxt, _ = lfilter([self.c[j, i]], [1.0, -self.phi[i]], x, axis=-1,
                                 zi=(self.phi[i] * b[:, j, i])[:, None])
                out[:, :, j] += np.concatenate([b[:, j, i:i + 1], nxt[:, :-1]], axis=1)
                b[:, j, i] = nxt[:, -1]
        return out

    def sensor_linear(self):
        p, K = self.dims.p, self.K
        F = np.diag(np.tile(self.phi, p))
        G = np.diag(self.c.reshape(-1))
        H = np.kron(np.eye(p), np.ones((1, K)))
        return F, G, H
