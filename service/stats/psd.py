"""Welch power spectral density with equivalent degrees of freedom and chi-squared intervals.

Conventions:

* ``psd`` is ONE-SIDED and per hertz: units of x squared per Hz, an estimate of the one-sided
  density G(f) = 2 S(f) at every bin f_k = k fs / nperseg in [0, fs/2], DC and Nyquist
  included (scipy leaves those two bins undoubled; they are doubled here so that every value
  estimates the same density). For white noise of per-sample variance s^2 sampled at fs,
  G = 2 s^2 / fs. It integrates over [0, fs/2] to the (window-weighted) mean square of the
  detrended data: sum_k w_k psd_k df with df = fs/nperseg and w_k = 1 except 1/2 at DC and
  Nyquist (:meth:`PsdEstimate.mean_square`); with a boxcar window, one segment and
  ``detrend="constant"`` that is exactly the sample variance (ddof = 0).
* ``detrend="constant"`` removes each segment's mean, which also removes power from the bins
  inside the window's main lobe around DC: for a Hann window bin 1 expects 5/6 of a locally
  white spectrum, bin 0 nothing. Use ``detrend="none"`` on zero-mean data when those bins
  matter.
* The computation is :func:`scipy.signal.welch` (Welch 1967; Percival & Walden 1993, sec. 6.17,
  "WOSA"): segments of ``nperseg`` samples, shifted by n = nperseg - noverlap, each windowed,
  detrended and Fourier transformed; their periodograms are averaged.
* ``dof`` is the equivalent chi-squared degrees of freedom nu of each bin: psd * nu / G is
  approximately chi2(nu). For one interior bin it is Percival & Walden (1993) eq. (292b),

      nu = 2 N_B / (1 + 2 sum_{r=1}^{N_B - 1} (1 - r/N_B) |sum_t h_t h_{t + r n}|^2),

  h the window normalised to sum h^2 = 1 and N_B the number of segments. Computed here from
  the general Gaussian covariance of averaged WOSA ordinates (see :func:`_wosa_dof`), which also
  gives the DC and Nyquist bins their half dof (their ordinates are real, chi2 with nu/2) and
  the dof of a band average of correlated neighbouring bins (:func:`psd_log_bins`,
  :func:`psd_band`). It assumes the spectrum is locally flat over the window's bandwidth and
  ignores the detrending's effect on the lowest one or two bins.

References:
    P. D. Welch, "The use of fast Fourier transform for the estimation of power spectra",
    IEEE Trans. Audio Electroacoust. 15 (1967) 70-73.
    D. B. Percival and A. T. Walden, *Spectral Analysis for Physical Applications*, Cambridge
    University Press, 1993, sec. 6.17 and eq. (292b).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import signal as _sig
from scipy import stats as _sps

from .errors import StatsError, as_series, choice, positive_float, positive_int, probability

__all__ = ["PsdEstimate", "welch", "psd_log_bins", "psd_band", "log_bin_groups", "window_autocorrelation"]

_DETRENDS = ("constant", "linear", "none")


@dataclass(frozen=True)
class PsdEstimate:
    """A one-sided Welch PSD estimate.

    Attributes:
        f: bin frequencies [Hz] (bin centres; after :func:`psd_log_bins`, the mean frequency of
            the averaged bins).
        psd: one-sided PSD [x units^2 / Hz]; integrates over [0, fs/2] to the mean square.
        dof: equivalent chi-squared degrees of freedom per bin (DC and Nyquist: half).
        n_segments: number of averaged segments N_B.
        nperseg: segment length [samples].
        fs: sample rate [Hz].
        window: window name passed to scipy.signal.get_window.
        noverlap: overlap between segments [samples].
        bins: for an averaged estimate, the number of raw bins behind each value (else ones).
    """

    f: np.ndarray
    psd: np.ndarray
    dof: np.ndarray
    n_segments: int
    nperseg: int
    fs: float
    window: str
    noverlap: int
    bins: np.ndarray

    def mean_square(self) -> float:
        """Integral of the raw estimate over [0, fs/2]: sum_k w_k psd_k df, w = 1/2 at DC and
        Nyquist (the mean square of the windowed, detrended segments, averaged)."""
        _require_raw(self, "self")
        w = np.ones(self.psd.size)
        w[0] = 0.5
        if self.nperseg % 2 == 0:
            w[-1] = 0.5
        return float(np.dot(w, self.psd)) * self.fs / self.nperseg

    def ci(self, conf: float = 0.95) -> tuple[np.ndarray, np.ndarray]:
        """Equal-tail chi-squared interval for the true PSD in each bin:
        lo = psd nu / chi2.ppf(1 - a/2, nu), hi = psd nu / chi2.ppf(a/2, nu), a = 1 - conf."""
        conf = probability(conf, "conf")
        a = 1.0 - conf
        lo = self.psd * self.dof / _sps.chi2.ppf(1.0 - a / 2.0, self.dof)
        hi = self.psd * self.dof / _sps.chi2.ppf(a / 2.0, self.dof)
        return lo, hi

    def band(self, psd_true, conf: float = 0.95) -> tuple[np.ndarray, np.ndarray]:
        """Where the estimate should fall if the true PSD is ``psd_true`` (array or scalar):
        psd_true chi2.ppf(a/2, nu)/nu .. psd_true chi2.ppf(1 - a/2, nu)/nu."""
        conf = probability(conf, "conf")
        a = 1.0 - conf
        s = np.asarray(psd_true, dtype=np.float64)
        return s * _sps.chi2.ppf(a / 2.0, self.dof) / self.dof, s * _sps.chi2.ppf(1.0 - a / 2.0, self.dof) / self.dof


def welch(
    x,
    fs: float,
    nperseg: int | None = None,
    overlap: float = 0.5,
    window: str = "hann",
    detrend: str = "constant",
) -> PsdEstimate:
    """One-sided Welch PSD of ``x`` sampled at ``fs`` Hz (see the module docstring).

    Args:
        x: samples, 1-D, finite.
        fs: sample rate [Hz].
        nperseg: segment length; ``None`` for min(256, len(x)) as scipy.
        overlap: fraction of a segment shared with the next, in [0, 1); noverlap =
            round(overlap * nperseg).
        window: any name :func:`scipy.signal.get_window` accepts (periodic form, as welch).
        detrend: ``"constant"`` (remove each segment's mean), ``"linear"`` or ``"none"``.
    """
    xx = as_series(x, "x", min_len=2)
    fs = positive_float(fs, "fs")
    nperseg = min(256, xx.size) if nperseg is None else positive_int(nperseg, "nperseg", minimum=2)
    if nperseg > xx.size:
        raise StatsError(f"nperseg: {nperseg} is longer than x ({xx.size} samples)")
    try:
        ov = float(overlap)
    except (TypeError, ValueError):
        raise StatsError(f"overlap: expected a fraction in [0, 1), found {overlap!r}") from None
    if not 0.0 <= ov < 1.0:
        raise StatsError(f"overlap: expected a fraction in [0, 1), found {overlap!r}")
    detrend = choice(detrend, "detrend", _DETRENDS)
    if not isinstance(window, str):
        raise StatsError(f"window: expected a window name, found {window!r}")
    try:
        h = _sig.get_window(window, nperseg)
    except ValueError as exc:
        raise StatsError(f"window: {window!r} is not a scipy window ({exc})") from None
    noverlap = min(int(round(ov * nperseg)), nperseg - 1)
    f, p = _sig.welch(
        xx,
        fs=fs,
        window=h,
        nperseg=nperseg,
        noverlap=noverlap,
        detrend=False if detrend == "none" else detrend,
        return_onesided=True,
        scaling="density",
        average="mean",
    )
    p = p.copy()
    p[0] *= 2.0  # scipy's DC and Nyquist bins hold G/2; make every bin estimate G
    if nperseg % 2 == 0:
        p[-1] *= 2.0
    step = nperseg - noverlap
    n_seg = (xx.size - noverlap) // step
    a2 = _window_lag_spectra(h, step, n_seg)
    # one bin j: Var/S^2 = sum_r w_r (|A(r n, 0)|^2 + |A(r n, 2j)|^2) / N_B^2 (see _wosa_dof)
    two_j = (2 * np.arange(f.size)) % nperseg
    var = sum(weight * (a[0] + a[two_j]) for weight, a in a2) / float(n_seg) ** 2
    dof = 2.0 / var
    return PsdEstimate(
        f=f,
        psd=p,
        dof=dof,
        n_segments=int(n_seg),
        nperseg=int(nperseg),
        fs=fs,
        window=window,
        noverlap=int(noverlap),
        bins=np.ones(f.size, dtype=np.int64),
    )


def psd_log_bins(est: PsdEstimate, bins_per_decade: int) -> PsdEstimate:
    """Average neighbouring bins into logarithmically spaced bands for log-log display.

    Bins with f > 0 are grouped into bands (10^((k-1)/b), 10^(k/b)] Hz, b = bins_per_decade
    (upper edge included, so a Nyquist frequency on a band edge stays with its neighbours).
    Each band's value is the plain mean of its bins, its frequency their mean frequency, its
    ``bins`` their number and its dof the equivalent dof of that mean: the dofs of the bins
    add when the bins are uncorrelated (boxcar, no overlap), and add to less when the window
    makes neighbours correlate (for one Hann segment adjacent ordinates correlate by 4/9).
    The DC bin is dropped.
    """
    _require_raw(est, "est")
    return _average_groups(est, log_bin_groups(est.f, bins_per_decade))


def log_bin_groups(f, bins_per_decade: int) -> list[np.ndarray]:
    """Indices of the raw bins (f > 0) in each log band of :func:`psd_log_bins`, so a model's
    expected values can be averaged over exactly the same bins."""
    bpd = positive_int(bins_per_decade, "bins_per_decade")
    f = np.asarray(f, dtype=np.float64)
    idx = np.flatnonzero(f > 0)
    key = np.ceil(bpd * np.log10(f[idx]) - 1e-9).astype(np.int64)
    edges = np.flatnonzero(np.diff(key)) + 1
    return np.split(idx, edges)


def psd_band(est: PsdEstimate, f_lo: float, f_hi: float) -> tuple[float, float]:
    """Mean PSD over the raw bins with f_lo <= f <= f_hi and its equivalent dof."""
    _require_raw(est, "est")
    sel = np.flatnonzero((est.f >= float(f_lo)) & (est.f <= float(f_hi)))
    if sel.size == 0:
        raise StatsError(f"f_lo, f_hi: no bin in [{f_lo!r}, {f_hi!r}] Hz")
    out = _average_groups(est, [sel])
    return float(out.psd[0]), float(out.dof[0])


# --------------------------------------------------------------------------------------------


def window_autocorrelation(w: np.ndarray) -> np.ndarray:
    """c_w(d) = sum_n w_{n+d} w_n, d = 0..len(w)-1 (by FFT: O(L log L), for tapers of any length)."""
    w = np.asarray(w, dtype=np.float64)
    n = w.size
    return np.fft.irfft(np.abs(np.fft.rfft(w, 2 * n)) ** 2, 2 * n)[:n]


def _require_raw(est, name: str) -> None:
    if not isinstance(est, PsdEstimate):
        raise StatsError(f"{name}: expected a PsdEstimate, found {type(est).__name__}")
    if np.any(est.bins != 1):
        raise StatsError(f"{name}: expected a raw Welch estimate, found one already averaged")


def _average_groups(est: PsdEstimate, groups) -> PsdEstimate:
    h = _sig.get_window(est.window, est.nperseg)
    step = est.nperseg - est.noverlap
    a2 = _window_lag_spectra(h, step, est.n_segments)
    f = np.array([est.f[g].mean() for g in groups])
    p = np.array([est.psd[g].mean() for g in groups])
    dof = np.array([_wosa_dof(a2, g, est.n_segments, est.nperseg) for g in groups])
    return PsdEstimate(
        f=f,
        psd=p,
        dof=dof,
        n_segments=est.n_segments,
        nperseg=est.nperseg,
        fs=est.fs,
        window=est.window,
        noverlap=est.noverlap,
        bins=np.array([g.size for g in groups], dtype=np.int64),
    )


def _window_lag_spectra(h: np.ndarray, step: int, n_seg: int) -> list[tuple[int, np.ndarray]]:
    """[(weight_r, |A(r step, l)|^2 for l = 0..nperseg-1)] for the segment lags r that overlap.

    A(s, l) = sum_t h_t h_{t-s} e^{-2 pi i l t / nperseg} / sum_t h_t^2 is the covariance,
    relative to the spectrum level, between the DFTs at bins j and j - l of two segments s
    samples apart (Gaussian, locally white data); weight_r = (N_B - |r|) counts segment pairs
    r apart (r and -r together, hence 2 (N_B - r) for r > 0)."""
    n = h.size
    norm = float(np.dot(h, h))
    out = []
    for r in range(0, n_seg):
        s = r * step
        if s >= n:
            break
        prod = np.zeros(n)
        prod[s:] = h[s:] * h[: n - s]
        a = np.fft.fft(prod) / norm
        weight = float(n_seg) if r == 0 else 2.0 * (n_seg - r)
        out.append((weight, np.abs(a) ** 2))
    return out


def _wosa_dof(a2, group: np.ndarray, n_seg: int, nperseg: int) -> float:
    """Equivalent dof of the mean of the WOSA ordinates at the contiguous bins ``group``.

    Var(mean)/S^2 = (1/(K^2 N_B^2)) sum_{j,k in group} sum_r w_r (|A(r n, j - k)|^2 +
    |A(r n, j + k)|^2); nu = 2 / that (Gaussian data, spectrum flat across the group). The
    second (mirror) term matters only near DC and Nyquist; for one interior bin this is
    Percival & Walden (1993) eq. (292b), at DC and Nyquist half of it. The double sum over a
    contiguous group is a sum over the K-|l| pairs at each difference l (and likewise sums)."""
    g = np.asarray(group, dtype=np.int64)
    K = g.size
    if K > 1 and np.any(np.diff(g) != 1):
        raise StatsError("group: expected contiguous bins")
    lag = np.arange(-(K - 1), K)
    pairs = (K - np.abs(lag)).astype(np.float64)  # pairs (j, k) with j - k = lag, or with
    diff_idx = lag % nperseg  # j + k = 2 g0 + K - 1 + lag
    sum_idx = (2 * int(g[0]) + K - 1 + lag) % nperseg
    var = 0.0
    for weight, a in a2:
        var += weight * float(np.dot(pairs, a[diff_idx] + a[sum_idx]))
    var /= (K * n_seg) ** 2
    return 2.0 / var
