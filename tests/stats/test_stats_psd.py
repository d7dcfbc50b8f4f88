"""Welch PSD (noiselab.stats.psd): levels, degrees of freedom, intervals, integral.

Tolerances come from the estimator's own distribution: psd * dof / G ~ chi2(dof) per bin
(Percival & Walden 1993, eq. (292b)); counts of bins outside a band are binomial when the bins
are independent. With a Hann window and 50 % overlap, bins three apart are exactly
uncorrelated (the squared window and the product of overlapping half-windows have only
harmonics 0..2), so every third bin is used for counting.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal, stats

from noiselab.stats import StatsError, psd_band, psd_log_bins, welch


def binomial_region(n: int, p: float, level: float = 0.999) -> tuple[float, float]:
    """Acceptance region for a Binomial(n, p) count at the given level (two-sided)."""
    a = (1.0 - level) / 2.0
    return tuple(stats.binom.ppf([a, 1.0 - a], n, p))


def ar1(phi: float, sigma_e: float, n: int, rng) -> np.ndarray:
    """Stationary AR(1): x_t = phi x_{t-1} + e_t, Var(e) = sigma_e^2, x_0 from the stationary law."""
    e = sigma_e * rng.standard_normal(n)
    x0 = sigma_e / np.sqrt(1.0 - phi * phi) * rng.standard_normal()
    x, _ = signal.lfilter([1.0], [1.0, -phi], e, zi=[phi * x0])
    return x


def test_white_noise_level_is_two_sigma2_over_fs():
    """White noise of variance s^2 at fs: one-sided G = 2 s^2 / fs at every bin."""
    rng = np.random.default_rng(11)
    fs, s = 250.0, 0.3
    est = welch(s * rng.standard_normal(2**17), fs, nperseg=1024)
    level = 2 * s * s / fs
    # the band average over bins 2..Nyquist (bin 0/1 are touched by the mean removal) and its
    # equivalent dof: the true level lies in the 99.9 % chi-squared interval
    mean, dof = psd_band(est, 2 * fs / 1024, fs / 2)
    lo, hi = mean * dof / stats.chi2.ppf([0.9995, 0.0005], dof)
    assert lo <= level <= hi
    assert dof > 20_000  # a meaningful test: relative half-width ~ 3.3 / sqrt(dof / 2) < 3 %
    # DC-side and Nyquist bins estimate the same density (not half of it)
    assert est.psd[-1] == pytest.approx(level, rel=5 * np.sqrt(2 / est.dof[-1]))


def test_dof_is_percival_walden_292b():
    rng = np.random.default_rng(0)
    nperseg, n = 512, 20_000
    est = welch(rng.standard_normal(n), 1.0, nperseg=nperseg, overlap=0.5)
    step = nperseg - nperseg // 2
    nb = (n - nperseg // 2) // step
    assert est.n_segments == nb
    h = signal.get_window("hann", nperseg)
    h = h / np.sqrt(np.sum(h * h))
    # P&W (292b): nu = 2 N_B / (1 + 2 sum_{m=1}^{N_B-1} (1 - m/N_B) |sum_t h_t h_{t+m n}|^2)
    acc = sum(
        (1 - m / nb) * np.dot(h[m * step :], h[: nperseg - m * step]) ** 2
        for m in range(1, nb)
        if m * step < nperseg
    )
    nu = 2 * nb / (1 + 2 * acc)
    np.testing.assert_allclose(est.dof[3:-3], nu, rtol=1e-12)
    assert est.dof[0] == pytest.approx(nu / 2, rel=1e-12)
    assert est.dof[-1] == pytest.approx(nu / 2, rel=1e-12)
    # no overlap, boxcar: independent periodograms, chi2 with 2 N_B dof exactly
    box = welch(rng.standard_normal(n), 1.0, nperseg=nperseg, overlap=0.0, window="boxcar")
    np.testing.assert_allclose(box.dof[1:-1], 2 * (n // nperseg), rtol=1e-12)


def test_fraction_outside_95_band_on_white_noise():
    rng = np.random.default_rng(2024)
    fs = 1.0
    est = welch(rng.standard_normal(2**18), fs, nperseg=8192)
    lo, hi = est.ci(0.95)
    level = 2.0 / fs
    sel = slice(2, -1, 3)  # independent bins, away from DC and Nyquist
    outside = int(np.sum((level < lo[sel]) | (level > hi[sel])))
    count = lo[sel].size
    a, b = binomial_region(count, 0.05)
    assert a <= outside <= b, (outside, count)
    assert count > 1000


def test_integral_equals_variance():
    rng = np.random.default_rng(3)
    x = 5.0 + 3.0 * rng.standard_normal(4096)
    # one boxcar segment, mean removed: Parseval gives exactly the sample variance (ddof 0)
    est = welch(x, 10.0, nperseg=4096, window="boxcar", detrend="constant")
    assert est.mean_square() == pytest.approx(np.var(x), rel=1e-12)
    # non-overlapping boxcar segments without detrending: the mean square of the data used
    est = welch(x, 10.0, nperseg=512, overlap=0.0, window="boxcar", detrend="none")
    assert est.mean_square() == pytest.approx(np.mean(x * x), rel=1e-12)
    # Hann, 50 % overlap: the average over segments of the window-weighted mean square
    est = welch(x, 10.0, nperseg=512)
    h = signal.get_window("hann", 512)
    segs = [x[i : i + 512] for i in range(0, x.size - 512 + 1, 256)]
    direct = np.mean([np.sum((h * (sg - sg.mean())) ** 2) / np.sum(h * h) for sg in segs])
    assert est.mean_square() == pytest.approx(direct, rel=1e-12)


def test_ar1_against_analytic_psd():
    """AR(1) x_t = phi x_{t-1} + e_t: G(f) = 2 sigma_e^2 / (fs |1 - phi e^{-2 pi i f/fs}|^2)."""
    rng = np.random.default_rng(99)
    phi, sigma_e, fs = 0.6, 0.5, 20.0
    est = welch(ar1(phi, sigma_e, 2**18, rng), fs, nperseg=2048)
    g = 2 * sigma_e**2 / (fs * np.abs(1 - phi * np.exp(-2j * np.pi * est.f / fs)) ** 2)
    lo, hi = est.ci(0.95)
    sel = slice(2, -1, 3)
    outside = int(np.sum((g[sel] < lo[sel]) | (g[sel] > hi[sel])))
    a, b = binomial_region(lo[sel].size, 0.05)
    assert a <= outside <= b
    # log-binned (dof of averaged, correlated bins): every band within its own interval, at a
    # level Bonferroni-corrected over the bands
    lb = psd_log_bins(est, 8)
    # bands are consecutive runs of the f > 0 bins, lb.bins long: average G over the same bins
    runs = np.split(g[est.f > 0], np.cumsum(lb.bins)[:-1])
    g_lb = np.array([run.mean() for run in runs])
    keep = lb.f > 1.5 * fs / 2048  # drop the first band (bin 1 alone, mean-removal bias)
    lo_b, hi_b = lb.ci(1 - 0.001 / keep.sum())
    assert np.all((lo_b[keep] <= g_lb[keep]) & (g_lb[keep] <= hi_b[keep]))
    assert np.all(np.diff(lb.bins) >= 0) and lb.bins[-1] > 100  # widening bands up to Nyquist
    assert lb.f[-1] < fs / 2 < lb.f[-1] * 10 ** (1 / 8)


def test_log_bin_dof_accounts_for_hann_correlation():
    """Averaging K adjacent Hann bins: the dof is below K nu (neighbours correlate by 4/9)
    and matches the Monte Carlo variance of the band average."""
    rng = np.random.default_rng(8)
    vals = []
    est = None
    for _ in range(300):
        est = welch(rng.standard_normal(4096), 1.0, nperseg=256)
        vals.append(np.mean(est.psd[40:80]))
    mean, dof = psd_band(est, est.f[40], est.f[79])
    assert dof < 40 * est.dof[60]
    v = np.array(vals) / 2.0  # normalised: true level 2
    # sample variance of 300 draws vs 2/dof: chi2(299) bounds on the ratio
    ratio = np.var(v, ddof=1) / (2.0 / dof)
    a, b = stats.chi2.ppf([0.0005, 0.9995], 299) / 299
    assert a <= ratio <= b


@pytest.mark.parametrize(
    "call, culprit",
    [
        (lambda: welch(np.ones(10), 1.0, nperseg=20), "nperseg"),
        (lambda: welch(np.ones(100), -1.0), "fs"),
        (lambda: welch(np.ones(100), 1.0, overlap=1.0), "overlap"),
        (lambda: welch(np.ones(100), 1.0, detrend="quadratic"), "detrend"),
        (lambda: welch(np.ones(100), 1.0, window="nosuchwindow"), "window"),
        (lambda: welch(np.ones(100), 1.0).ci(95), "conf"),
        (lambda: psd_log_bins(welch(np.ones(100), 1.0), 0), "bins_per_decade"),
    ],
)
def test_bad_arguments_name_the_culprit(call, culprit):
    with pytest.raises(StatsError, match=f"^{culprit}:"):
        call()
