"""Allan-family deviations of rate data, with Stable32-compatible noise identification,
Greenhall equivalent degrees of freedom and chi-squared confidence bounds.

Symbols and names (NIST SP 1065 = W. J. Riley, *Handbook of Frequency Stability Analysis*, 2008):

==========  ===========  ====================================================================
paper       here         meaning
==========  ===========  ====================================================================
y_i         ``y``        rate samples (fractional frequency, or any rate such as a gyro's
                         deg/s) taken every tau_0 = 1/``rate`` seconds, i = 0..N-1
x_i         ``x``        phase (integrated rate): x_0 = 0, x_{i+1} = x_i + tau_0 y_i, so
                         N + 1 phase points; units of y times seconds
tau_0       ``1/rate``   sample interval [s]
m           ``m``        averaging factor, tau = m tau_0 [s]
sigma_y     ``dev``      deviation, same units as y
alpha       ``alpha``    power-law exponent of the one-sided rate PSD S_y(f) ~ h_alpha f^alpha
                         (2 white PM, 1 flicker PM, 0 white FM, -1 flicker FM, -2 random-walk FM)
edf         ``edf``      equivalent chi-squared degrees of freedom of dev**2
==========  ===========  ====================================================================

Estimators (all with the 1/2 of the two-sample variance, so white rate noise of per-sample
standard deviation s has sigma_y(tau) = s / sqrt(m)):

* ``adev``   non-overlapping Allan deviation, SP 1065 eq. (6)/(7); n = floor(N/m) - 1 terms.
* ``oadev``  fully overlapping Allan deviation, SP 1065 eq. (11) (phase form
             sigma^2 = sum_{i}(x_{i+2m} - 2x_{i+m} + x_i)^2 / (2 (N+1-2m) tau^2));
             n = N - 2m + 1 terms.
* ``mdev``   modified Allan deviation, SP 1065 eq. (14)/(15); n = N - 3m + 2 terms.

"n" is the number of terms as Stable32 prints it in its "#" column.

Computation: the phase as one cumulative sum of the mean-removed rate, and each variance a sum
of squared second differences on it, O(N) per tau (:mod:`.allan_sums`).

Precision: the second difference is a difference of cumulative sums, so its absolute rounding
error is about eps * max|sum (y - mean y)| (eps = 2.2e-16). Data with a large constant offset
(e.g. frequency normalised to 1.0 instead of 0) would otherwise lose digits; Stable32 itself
loses about four digits that way (see tests/stats/test_stats_allan.py).

Noise identification (``alpha``) as Stable32 does it: :mod:`.noise_id`. Confidence: the
Greenhall & Riley (2003) equivalent degrees of freedom and the chi-squared interval,
:mod:`.edf`. The IEEE Std 952 slope readings of a deviation curve: :mod:`.ieee952`.

References:
    NIST SP 1065: W. J. Riley, Handbook of Frequency Stability Analysis, 2008.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .allan_sums import PhaseSums, rate_sums
from .edf import ONE_SIGMA_CONF, chi2_bounds, edf_greenhall
from .errors import StatsError, as_series, choice, positive_float, probability
from .noise_id import alpha_override, identify_alpha

__all__ = [
    "AllanResult",
    "adev",
    "allan_taus",
    "mdev",
    "oadev",
    "oadev_from_phase",
]

# Stable32 limits the largest averaging factor to N / stop_ratio (Riley, "Evolution of frequency
# stability analysis software", table III); this reproduces the last row of its octave tables.
_STOP_RATIO = {"adev": 5, "oadev": 4, "mdev": 4}
# Estimator shape for the EDF: d (difference order), modified, overlapping.
_SHAPE = {"adev": (2, False, False), "oadev": (2, False, True), "mdev": (2, True, True)}
_KINDS = ("adev", "oadev", "mdev")


# --------------------------------------------------------------------------------------------
# result


@dataclass(frozen=True)
class AllanResult:
    """Allan-family deviation at several averaging times.

    Attributes:
        kind: ``"adev"``, ``"oadev"`` or ``"mdev"``.
        rate: sample rate of the input [Hz] (tau_0 = 1/rate).
        taus: averaging times tau = m / rate [s].
        m: integer averaging factors.
        dev: deviation sigma(tau), same units as the rate data y.
        n: number of terms in each estimate (Stable32's "#").
        alpha: identified (or given) power-law noise exponent of S_y(f) at each tau (int).
        edf: Greenhall equivalent degrees of freedom of dev**2.
        lo, hi: chi-squared bounds of dev at confidence ``conf`` (two-sided, equal tails).
        conf: the confidence level of ``lo``/``hi``.
    """

    kind: str
    rate: float
    taus: np.ndarray
    m: np.ndarray
    dev: np.ndarray
    n: np.ndarray
    alpha: np.ndarray
    edf: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    conf: float

    def bounds(self, conf: float = ONE_SIGMA_CONF) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) chi-squared bounds of ``dev`` at another confidence level."""
        return chi2_bounds(self.dev, self.edf, conf)


# --------------------------------------------------------------------------------------------
# public estimators


def adev(y, rate: float, taus="octave", *, conf: float = ONE_SIGMA_CONF, alpha=None) -> AllanResult:
    """Non-overlapping Allan deviation of rate data ``y`` sampled at ``rate`` Hz.

    sigma^2(tau) = 1/(2 n) sum_k (ybar_{k+1} - ybar_k)^2 over the n = floor(N/m) - 1 pairs of
    adjacent non-overlapping m-sample averages (NIST SP 1065 eq. (6); phase form eq. (7)).

    Args:
        y: rate samples (fractional frequency or any rate), 1-D, finite.
        rate: sample rate [Hz].
        taus: ``"octave"`` (m = 1, 2, 4, ... up to N/5 as Stable32), ``"all"`` (every m up to
            N/5) or an array of averaging times [s], each a whole multiple of 1/rate.
        conf: confidence level of ``lo``/``hi`` (default Stable32's 0.683).
        alpha: ``None`` to identify the noise type at each tau, or an int / per-tau ints to
            impose it (affects only ``edf``, ``lo``, ``hi``).
    """
    return _run("adev", rate_sums(y, rate), taus, conf, alpha)


def oadev(y, rate: float, taus="octave", *, conf: float = ONE_SIGMA_CONF, alpha=None) -> AllanResult:
    """Fully overlapping Allan deviation of rate data (NIST SP 1065 eq. (11)).

    sigma^2(tau) = 1/(2 tau^2 n) sum_{i=0}^{n-1} (x_{i+2m} - 2 x_{i+m} + x_i)^2,
    n = N - 2m + 1, x the phase of y. ``taus="octave"``/``"all"`` stop at m = N/4 (Stable32).
    See :func:`adev` for the arguments.
    """
    return _run("oadev", rate_sums(y, rate), taus, conf, alpha)


def mdev(y, rate: float, taus="octave", *, conf: float = ONE_SIGMA_CONF, alpha=None) -> AllanResult:
    """Modified Allan deviation of rate data (NIST SP 1065 eq. (14)).

    Mod sigma^2(tau) = 1/(2 m^2 tau^2 n) sum_{j=0}^{n-1} [sum_{i=j}^{j+m-1}
    (x_{i+2m} - 2 x_{i+m} + x_i)]^2, n = N - 3m + 2. ``taus="octave"``/``"all"`` stop at N/4.
    See :func:`adev` for the arguments.
    """
    return _run("mdev", rate_sums(y, rate), taus, conf, alpha)


def oadev_from_phase(
    x, rate: float, taus="octave", *, conf: float = ONE_SIGMA_CONF, alpha=None
) -> AllanResult:
    """Overlapping Allan deviation of phase data ``x`` (integrated rate, e.g. time error [s]
    for clocks or angle for a gyro), N + 1 points sampled at ``rate`` Hz.

    Identical to :func:`oadev` applied to the rate y_i = (x_{i+1} - x_i) * rate. A straight
    line is removed from x first (the estimator is invariant to it; it keeps the numbers small).
    """
    rate = positive_float(rate, "rate")
    xx = as_series(x, "x", min_len=4)  # as for rate data: 3 rate samples
    n = xx.size - 1
    k = np.arange(n + 1, dtype=np.float64)
    line = xx[0] + (xx[-1] - xx[0]) * (k / n)
    s = (xx - line) * rate  # phase in units of (rate data) * samples
    return _run("oadev", PhaseSums(s, rate), taus, conf, alpha)


def allan_taus(n_samples: int, rate: float, kind: str = "oadev", taus="octave") -> np.ndarray:
    """Averaging factors m that ``taus`` selects for ``n_samples`` rate samples (see
    :func:`adev` for the keywords)."""
    kind = choice(kind, "kind", _KINDS)
    return _averaging_factors(kind, int(n_samples), positive_float(rate, "rate"), taus)


def _averaging_factors(kind: str, n: int, rate: float, taus) -> np.ndarray:
    d, modified, _ = _SHAPE[kind]
    # largest m leaving at least one term: adev/oadev 2m <= N, mdev 3m <= N + 1
    m_max_valid = (n + 1) // 3 if modified else n // d
    if isinstance(taus, str):
        taus = choice(taus, "taus", ("octave", "all"))
        m_stop = max(1, n // _STOP_RATIO[kind])
        m_stop = min(m_stop, m_max_valid)
        if m_stop < 1:
            raise StatsError(f"y: {n} samples are too few for {kind}")
        if taus == "octave":
            return 2 ** np.arange(int(np.floor(np.log2(m_stop))) + 1, dtype=np.int64)
        return np.arange(1, m_stop + 1, dtype=np.int64)
    try:
        t = np.atleast_1d(np.asarray(taus, dtype=np.float64))
    except (TypeError, ValueError):
        raise StatsError(f"taus: expected 'octave', 'all' or an array of seconds, found {taus!r}") from None
    if t.ndim != 1 or t.size == 0 or not np.all(np.isfinite(t)):
        raise StatsError(f"taus: expected a non-empty 1-D array of finite seconds, found {taus!r}")
    mf = t * rate
    m = np.rint(mf).astype(np.int64)
    off = np.abs(mf - m) > 1e-6 * np.maximum(1.0, np.abs(mf))
    if np.any(off) or np.any(m < 1):
        bad = float(t[np.flatnonzero(off | (m < 1))[0]])
        raise StatsError(f"taus: {bad!r} s is not a positive whole multiple of 1/rate = {1.0 / rate!r} s")
    if np.any(m > m_max_valid):
        bad = float(t[np.flatnonzero(m > m_max_valid)[0]])
        raise StatsError(f"taus: {bad!r} s needs more than the {n} samples given for {kind} (m <= {m_max_valid})")
    return np.unique(m)


def _run(kind: str, series: PhaseSums, taus, conf, alpha) -> AllanResult:
    conf = probability(conf, "conf")
    ms = _averaging_factors(kind, series.n, series.rate, taus)
    var_fn = {"adev": series.avar, "oadev": series.oavar, "mdev": series.mvar}[kind]
    var = np.empty(ms.size)
    ns = np.empty(ms.size, dtype=np.int64)
    for i, m in enumerate(ms.tolist()):
        var[i], ns[i] = var_fn(m)
    dev = np.sqrt(var)
    alphas = identify_alpha(series, ms, ns) if alpha is None else alpha_override(alpha, ms.size)
    d, modified, overlapping = _SHAPE[kind]
    edf = np.array(
        [
            edf_greenhall(a, d, m, series.n + 1, overlapping=overlapping, modified=modified)
            for a, m in zip(alphas.tolist(), ms.tolist())
        ]
    )
    lo, hi = chi2_bounds(dev, edf, conf)
    return AllanResult(
        kind=kind,
        rate=series.rate,
        taus=ms / series.rate,
        m=ms,
        dev=dev,
        n=ns,
        alpha=alphas,
        edf=edf,
        lo=lo,
        hi=hi,
        conf=conf,
    )
