"""Sample ACF (noiselab.stats.acf): FFT equals the direct sum; Bartlett bands hold for AR(1).

References: Brockwell & Davis, Time Series: Theory and Methods (1991), eq. (7.2.5) and
example 7.2.3 (AR(1): w_kk = (1 + phi^2)(1 - phi^(2k))/(1 - phi^2) - 2 k phi^(2k)).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal, stats

from noiselab.stats import StatsError, acf, bartlett_se


def direct_autocovariance(x: np.ndarray, maxlag: int, demean: bool) -> np.ndarray:
    """O(N L) reference: r_k = (1/N) sum_{i=0}^{N-1-k} (x_i - xbar)(x_{i+k} - xbar)."""
    xc = x - x.mean() if demean else x
    n = x.size
    return np.array([np.dot(xc[: n - k], xc[k:]) / n for k in range(maxlag + 1)])


@pytest.mark.parametrize("n, maxlag", [(1000, 50), (1237, 1236), (4096, 300)])
@pytest.mark.parametrize("demean", [True, False])
def test_fft_equals_direct(n, maxlag, demean):
    rng = np.random.default_rng(n)
    x = 2.0 + np.cumsum(rng.standard_normal(n)) * 0.1 + rng.standard_normal(n)
    est = acf(x, maxlag, demean=demean)
    ref = direct_autocovariance(x, maxlag, demean)
    # relative to r_0: single lags may be near zero
    assert np.max(np.abs(est.r - ref)) <= 1e-12 * ref[0]
    np.testing.assert_allclose(est.rho, ref / ref[0], rtol=0, atol=1e-12)
    assert est.rho[0] == 1.0
    assert est.mean == (pytest.approx(x.mean(), rel=1e-15) if demean else 0.0)


def test_bartlett_se_ar1_closed_form():
    phi, n = 0.8, 5000
    L = 400  # phi^L ~ 1e-39: truncation of the reference is negligible
    se = bartlett_se(phi ** np.arange(L + 1), n)
    k = np.arange(101)
    w = (1 + phi**2) * (1 - phi ** (2 * k)) / (1 - phi**2) - 2 * k * phi ** (2 * k)
    np.testing.assert_allclose(se[:101], np.sqrt(w / n), rtol=1e-12, atol=1e-15)
    # white noise: 1/sqrt(n) at every lag > 0
    np.testing.assert_allclose(bartlett_se(np.r_[1.0, np.zeros(20)], 400)[1:], 0.05, rtol=1e-14)


def test_ar1_sample_acf_within_bartlett_bands():
    """Every lag 1..L inside rho^k +/- z se_k at a Bonferroni-corrected 99 % family level,
    and about 95 % of lags inside the plain 95 % band."""
    rng = np.random.default_rng(1)
    phi, n, L = 0.7, 20_000, 60
    e = rng.standard_normal(n)
    x0 = rng.standard_normal() / np.sqrt(1 - phi * phi)
    x, _ = signal.lfilter([1.0], [1.0, -phi], e, zi=[phi * x0])
    est = acf(x, L)
    rho_model = phi ** np.arange(L + 1)
    lo, hi = est.ci(1 - 0.01 / L, rho_ref=rho_model)
    inside = (lo <= est.rho) & (est.rho <= hi)
    assert np.all(inside[1:])
    # the band is real: at lag 1 its half-width is z sqrt((1 - phi^2)/n) ~ 0.02
    assert hi[1] - lo[1] < 0.05
    # a wrong model is rejected by the same band
    lo_w, hi_w = est.ci(1 - 0.01 / L, rho_ref=0.6 ** np.arange(L + 1))
    assert not np.all(((lo_w <= est.rho) & (est.rho <= hi_w))[1:])


def test_white_noise_fraction_outside_band():
    """White noise: sample autocorrelations at different lags are asymptotically independent
    N(0, 1/n) (Bartlett), so the count outside the 95 % band is binomial."""
    rng = np.random.default_rng(4)
    n, L = 50_000, 2000
    est = acf(rng.standard_normal(n), L)
    lo, hi = est.ci(0.95, rho_ref=np.r_[1.0, np.zeros(L)])
    outside = int(np.sum((est.rho[1:] < lo[1:]) | (est.rho[1:] > hi[1:])))
    a, b = stats.binom.ppf([0.0005, 0.9995], L, 0.05)
    assert a <= outside <= b


@pytest.mark.parametrize(
    "call, culprit",
    [
        (lambda: acf(np.ones(10), 10), "maxlag"),
        (lambda: acf([1.0, np.inf, 2.0], 1), "x"),
        (lambda: acf(np.arange(10.0), 3, demean="yes"), "demean"),
        (lambda: bartlett_se([0.5, 0.2], 100), "rho_ref"),
        (lambda: acf(np.arange(10.0), 3).ci(0.95, rho_ref=[1.0, 0.5]), "rho_ref"),
    ],
)
def test_bad_arguments_name_the_culprit(call, culprit):
    with pytest.raises(StatsError, match=f"^{culprit}:"):
        call()
