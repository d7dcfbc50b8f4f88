"""Sample autocovariance / autocorrelation by FFT, with Bartlett standard errors.

Conventions (Box & Jenkins; Brockwell & Davis, *Time Series: Theory and Methods*, 1991):

* ``r[k]`` is the BIASED autocovariance, per sample lag k (not per second),
  r_k = (1/N) sum_{i=0}^{N-1-k} (x_i - xbar)(x_{i+k} - xbar), k = 0..maxlag, in x units
  squared; r_0 is the variance with ddof = 0. The 1/N (not 1/(N-k)) normalisation makes the
  sequence positive semi-definite and is the estimator Bartlett's formula describes.
* ``rho[k] = r[k] / r[0]`` is the sample autocorrelation.
* Computed as the inverse FFT of the periodogram of the zero-padded (length >= 2N - 1) data,
  O(N log N), identical to the direct sum up to rounding.
* Bartlett's formula (Brockwell & Davis eq. (7.2.5), Theorem 7.2.1): for a linear process with
  autocorrelation rho, sqrt(N) (rho_hat_k - rho_k) is asymptotically normal with variance
  w_kk = sum_{j=1}^inf (rho_{k+j} + rho_{k-j} - 2 rho_k rho_j)^2. :func:`bartlett_se` returns
  sqrt(w_kk / N) from a reference sequence (a model's autocorrelation, or the sample's own),
  taken as zero beyond its last lag.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import fft as _fft
from scipy import stats as _sps

from .errors import StatsError, as_series, positive_int, probability

__all__ = ["AcfEstimate", "acf", "bartlett_se"]


@dataclass(frozen=True)
class AcfEstimate:
    """Sample autocovariance and autocorrelation.

    Attributes:
        lags: integer lags 0..maxlag [samples].
        r: biased autocovariance [x units^2].
        rho: autocorrelation r / r[0] (dimensionless).
        n: number of samples N.
        mean: the mean removed (0.0 when ``demean=False``).
    """

    lags: np.ndarray
    r: np.ndarray
    rho: np.ndarray
    n: int
    mean: float

    def ci(self, conf: float = 0.95, rho_ref=None) -> tuple[np.ndarray, np.ndarray]:
        """Two-sided normal band rho_ref +/- z se, se = :func:`bartlett_se` (rho_ref, n).

        With ``rho_ref`` a model's autocorrelation at lags 0..maxlag (or longer) this is where
        the sample ``rho`` should lie if the model is right; with ``rho_ref=None`` the sample's
        own ``rho`` is the reference, giving an approximate interval for the true rho."""
        conf = probability(conf, "conf")
        ref = self.rho if rho_ref is None else _as_rho(rho_ref, self.lags.size)
        se = bartlett_se(ref, self.n)[: self.lags.size]
        z = _sps.norm.ppf(0.5 * (1.0 + conf))
        centre = ref[: self.lags.size]
        return centre - z * se, centre + z * se


def acf(x, maxlag: int, demean: bool = True) -> AcfEstimate:
    """Biased sample autocovariance and autocorrelation of ``x`` at lags 0..maxlag.

    Args:
        x: samples, 1-D, finite.
        maxlag: largest lag [samples], < len(x).
        demean: remove the sample mean first (else use x as it is, e.g. a known-zero-mean
            residual).
    """
    xx = as_series(x, "x", min_len=2)
    n = xx.size
    maxlag = positive_int(maxlag, "maxlag", minimum=0)
    if maxlag >= n:
        raise StatsError(f"maxlag: expected < len(x) = {n}, found {maxlag}")
    if not isinstance(demean, (bool, np.bool_)):
        raise StatsError(f"demean: expected True or False, found {demean!r}")
    mean = float(xx.mean()) if demean else 0.0
    xc = xx - mean
    nfft = _fft.next_fast_len(2 * n - 1, real=True)
    spec = _fft.rfft(xc, nfft)
    r = _fft.irfft(spec.real**2 + spec.imag**2, nfft)[: maxlag + 1] / n
    r0 = r[0]
    rho = r / r0 if r0 > 0.0 else np.full(maxlag + 1, np.nan)
    return AcfEstimate(lags=np.arange(maxlag + 1), r=r, rho=rho, n=n, mean=mean)


def bartlett_se(rho_ref, n: int) -> np.ndarray:
    """Standard error of the sample autocorrelation at lags 0..L by Bartlett's formula.

    se_k = sqrt(w_kk / n), w_kk = sum_{j >= 1} (rho_{k+j} + rho_{|k-j|} - 2 rho_k rho_j)^2,
    with ``rho_ref`` (rho_0 = 1, lags 0..L) taken as zero beyond lag L (Brockwell & Davis
    eq. (7.2.5)). se_0 = 0. For white noise se_k = 1/sqrt(n); for AR(1), rho_k = phi^k,
    w_kk = (1 + phi^2)(1 - phi^(2k))/(1 - phi^2) - 2 k phi^(2k).
    """
    ref = _as_rho(rho_ref, None)
    n = positive_int(n, "n")
    L = ref.size - 1
    top = 2 * L + 1
    ext = np.concatenate([ref, np.zeros(L + 1)])  # rho_i for i = 0..2L+1, zero beyond L
    j = np.arange(1, top + 1)[None, :]  # for k <= L every term with j > 2L is zero
    w = np.empty(L + 1)
    rows = max(1, 4_000_000 // top)  # bound the k-by-j work array
    for k0 in range(0, L + 1, rows):
        k = np.arange(k0, min(L + 1, k0 + rows))[:, None]
        term = (
            ext[np.minimum(k + j, top)]
            + ext[np.minimum(np.abs(k - j), top)]
            - 2.0 * ref[k] * ext[np.minimum(j, top)]
        )
        w[k0 : k0 + k.shape[0]] = np.einsum("ij,ij->i", term, term)
    return np.sqrt(w / n)


def _as_rho(rho, size: int | None) -> np.ndarray:
    arr = as_series(rho, "rho_ref", min_len=1)
    if size is not None and arr.size < size:
        raise StatsError(f"rho_ref: expected at least {size} lags (0..maxlag), found {arr.size}")
    if abs(arr[0] - 1.0) > 1e-9:
        raise StatsError(f"rho_ref: expected rho_ref[0] == 1 (an autocorrelation), found {arr[0]!r}")
    return arr
