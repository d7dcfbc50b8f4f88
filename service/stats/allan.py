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

Computation. The phase is formed once by a cumulative sum of the mean-removed rate (every
estimator here is invariant to a constant rate offset, and removing it keeps the cumulative sum
small, see *precision* below); each second difference x_{i+2m} - 2x_{i+m} + x_i is then one
vectorised expression, so each tau costs O(N) whatever m is, and the modified variance's inner
sums of m second differences are a moving sum through one more cumulative sum.

Precision: the second difference is a difference of cumulative sums, so its absolute rounding
error is about eps * max|sum (y - mean y)| (eps = 2.2e-16). Data with a large constant offset
(e.g. frequency normalised to 1.0 instead of 0) would otherwise lose digits; Stable32 itself
loses about four digits that way (see tests/stats/test_stats_allan.py).

Noise identification (``alpha``), as Stable32 does it:

1. at least 30 rate averages at this m (floor(N/m) >= 30): the lag-1 autocorrelation method of
   Riley & Greenhall (2004), SP 1065 section 5.6 -- average y in non-overlapping groups of m,
   then difference d = 0, 1, 2 times until delta = r1/(1 + r1) < 0.25 (or d = dmax = 2);
   alpha = -round(2 delta) - 2d. r1 is the lag-1 autocorrelation with the biased (1/N)
   autocovariance over the (N - 1)-normalised sample variance, i.e. the usual r1 times (N-1)/N,
   which is what Stable32 computes (all 167 ACF-identified taus of the OCXO reference agree);
2. fewer than 30 averages: the B1 bias-ratio test (Barnes; Howe, Beard, Greenhall & Riley 2000,
   tables 3/4): B1 = (standard variance of the m-averages) / (non-overlapping Allan variance),
   compared with its expected value for each power law at N = n (the statistic's number of
   terms, not the number of averages: that is what reproduces Stable32, as the allantoolkit
   project also found), boundaries at the geometric means (arithmetic between mu = 2 and 1);
   when B1 says "phase noise" the ratio R(n) = Mod AVAR / AVAR separates white (alpha = 2)
   from flicker (alpha = 1) PM (NIST TN 1337 table A-6) -- for every kind here; whether
   Stable32 does so for adev/oadev too is not established by the reference tables;
3. too few points for B1 -- fewer than 7 averages, or fewer than 10 terms in the statistic:
   the dominant noise already identified at the previous (shorter) tau is carried forward (B1
   is used anyway when there is no previous tau, and white FM assumed when even that is
   impossible). These two thresholds are not documented by Stable32; they are inferred from
   its OCXO tables (the oadev table needs B1 at 8 averages and the carried type at 6 or
   fewer, 7 fits either; the adev table carries the type forward at n = 8 terms but not at
   n = 18), and this rule reproduces all 311 Alpha values of the four tables. "Previous"
   means the previous tau in the list asked for, so with an explicit tau list the alpha of
   the longest taus depends on which shorter taus are in it (as in Stable32).

Alpha is clipped to [-2, 2], the range where the Allan variance converges and the EDF tables
apply.

Confidence: edf from the Greenhall & Riley (2003) algorithm (:func:`edf_greenhall`), then the
chi-squared interval of SP 1065 eq. (45), dev * sqrt(edf / chi2.ppf((1 +/- conf)/2, edf)).
The default ``conf = 0.683`` is Stable32's "Confidence Factor = 0.683".

References:
    NIST SP 1065: W. J. Riley, Handbook of Frequency Stability Analysis, 2008.
    C. A. Greenhall and W. J. Riley, "Uncertainty of stability variances based on finite
    differences", Proc. 35th PTTI, 2003 (equation and table numbers below as cited by the
    allantools reference implementation, which this one matches to 1e-12).
    W. J. Riley and C. A. Greenhall, "Power law noise identification using the lag 1
    autocorrelation", Proc. 18th EFTF, 2004.
    D. A. Howe, R. L. Beard, C. A. Greenhall, W. J. Riley, "A total estimator of the Hadamard
    function used for GPS operations", Proc. 32nd PTTI, 2000 (B1 tables).
"""

from __future__ import annotations

from dataclasses import dataclass
from math import comb

import numpy as np
from scipy import special as _sps_special
from scipy import stats as _sps

from .errors import StatsError, as_series, choice, positive_float, probability

__all__ = [
    "FLICKER_FLOOR",
    "IEEE952_NAMES",
    "NOISE_NAMES",
    "NOISE_SLOPES",
    "ONE_SIGMA_CONF",
    "AllanResult",
    "SlopeReading",
    "adev",
    "allan_taus",
    "chi2_bounds",
    "edf_greenhall",
    "ieee952_readings",
    "mdev",
    "noise_id_lag1",
    "oadev",
    "oadev_from_phase",
]

#: Stable32's default "Confidence Factor" (a one-sigma interval).
ONE_SIGMA_CONF = 0.683

# Stable32 limits the largest averaging factor to N / stop_ratio (Riley, "Evolution of frequency
# stability analysis software", table III); this reproduces the last row of its octave tables.
_STOP_RATIO = {"adev": 5, "oadev": 4, "mdev": 4}
# Estimator shape for the EDF: d (difference order), modified, overlapping.
_SHAPE = {"adev": (2, False, False), "oadev": (2, False, True), "mdev": (2, True, True)}
_ACF_MIN_POINTS = 30  # lag-1 ACF needs >= 30 averages (Riley & Greenhall 2004)
_B1_MIN_POINTS = 7  # fewer averages: Stable32 carries the previous tau's noise type forward
_B1_MIN_TERMS = 10  # fewer terms in the statistic: likewise (inferred, see module docstring)
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
    return _run("adev", _rate_series(y, rate), taus, conf, alpha)


def oadev(y, rate: float, taus="octave", *, conf: float = ONE_SIGMA_CONF, alpha=None) -> AllanResult:
    """Fully overlapping Allan deviation of rate data (NIST SP 1065 eq. (11)).

    sigma^2(tau) = 1/(2 tau^2 n) sum_{i=0}^{n-1} (x_{i+2m} - 2 x_{i+m} + x_i)^2,
    n = N - 2m + 1, x the phase of y. ``taus="octave"``/``"all"`` stop at m = N/4 (Stable32).
    See :func:`adev` for the arguments.
    """
    return _run("oadev", _rate_series(y, rate), taus, conf, alpha)


def mdev(y, rate: float, taus="octave", *, conf: float = ONE_SIGMA_CONF, alpha=None) -> AllanResult:
    """Modified Allan deviation of rate data (NIST SP 1065 eq. (14)).

    Mod sigma^2(tau) = 1/(2 m^2 tau^2 n) sum_{j=0}^{n-1} [sum_{i=j}^{j+m-1}
    (x_{i+2m} - 2 x_{i+m} + x_i)]^2, n = N - 3m + 2. ``taus="octave"``/``"all"`` stop at N/4.
    See :func:`adev` for the arguments.
    """
    return _run("mdev", _rate_series(y, rate), taus, conf, alpha)


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
    return _run("oadev", _Series(s, rate), taus, conf, alpha)


def allan_taus(n_samples: int, rate: float, kind: str = "oadev", taus="octave") -> np.ndarray:
    """Averaging factors m that ``taus`` selects for ``n_samples`` rate samples (see
    :func:`adev` for the keywords)."""
    kind = choice(kind, "kind", _KINDS)
    return _averaging_factors(kind, int(n_samples), positive_float(rate, "rate"), taus)


def chi2_bounds(dev, edf, conf: float = ONE_SIGMA_CONF) -> tuple[np.ndarray, np.ndarray]:
    """Equal-tail chi-squared interval of a deviation with ``edf`` degrees of freedom.

    lo = dev sqrt(edf / chi2.ppf((1 + conf)/2, edf)), hi = dev sqrt(edf / chi2.ppf((1 - conf)/2,
    edf)) (NIST SP 1065 eq. (45)); e.g. conf = 0.683 uses the 0.8415 and 0.1585 quantiles.
    """
    conf = probability(conf, "conf")
    dev = np.asarray(dev, dtype=np.float64)
    edf = np.asarray(edf, dtype=np.float64)
    lo = dev * np.sqrt(edf / _sps.chi2.ppf(0.5 * (1.0 + conf), edf))
    hi = dev * np.sqrt(edf / _sps.chi2.ppf(0.5 * (1.0 - conf), edf))
    return lo, hi


def noise_id_lag1(z, dmax: int = 2) -> tuple[int, float, int]:
    """Lag-1 autocorrelation noise identification (Riley & Greenhall 2004; SP 1065 sec. 5.6).

    ``z`` is rate data already averaged to the tau of interest. Returns (alpha rounded,
    alpha as a float = -2 (delta + d), number of differences d). Applies to phase data as
    alpha + 2. r1 is scaled by (N-1)/N as Stable32 does (see module docstring).
    """
    zz = as_series(z, "z", min_len=3)
    d = 0
    while True:
        delta = _delta_lag1(zz)
        if delta < 0.25 or d >= dmax or zz.size < 4:
            return int(np.floor(-2.0 * delta + 0.5)) - 2 * d, -2.0 * (delta + d), d
        zz = np.diff(zz)
        d += 1


def edf_greenhall(
    alpha: int, d: int, m: int, n_phase: int, *, overlapping: bool, modified: bool
) -> float:
    """Equivalent degrees of freedom of a finite-difference stability variance.

    The algorithm of Greenhall & Riley (2003), section 5 (the one Stable32 uses): exact sums
    (BasicSum, eq. (10)) for up to J_max = 100 terms, the large-r approximations of their
    tables 1-3 beyond, and the exact white-PM formula for case 4.

    Args:
        alpha: power-law exponent of S_y(f), integer in [-4, 2] with alpha + 2d > 1.
        d: difference order (1 first difference, 2 Allan, 3 Hadamard).
        m: averaging factor.
        n_phase: number of phase points (N + 1 for N rate samples).
        overlapping: stride tau_0 (True) or tau (False).
        modified: modified (F = 1) or unmodified (F = m) variance.
    """
    alpha, d, m, n_phase = int(alpha), int(d), int(m), int(n_phase)
    if d not in (1, 2, 3):
        raise StatsError(f"d: expected 1, 2 or 3, found {d}")
    if not -4 <= alpha <= 2 or alpha + 2 * d <= 1:
        raise StatsError(f"alpha: expected an integer in [-4, 2] with alpha + 2d > 1, found {alpha} (d={d})")
    F = 1 if modified else m  # filter factor
    S = m if overlapping else 1  # stride factor
    L = m // F + m * d  # filter length in phase samples
    if n_phase < L + 1 or m < 1:
        raise StatsError(f"n_phase: {n_phase} phase points are too few for m={m}, d={d}")
    M = 1 + (S * (n_phase - L)) // m  # number of summands
    J = min(M, (d + 1) * S)
    r = M / S
    jmax = 100
    if modified:  # case 1: modified variances, all alpha
        if J <= jmax:
            inv = _basic_sum(J, M, S, 1, alpha, d) / (M * _sz(0.0, 1, alpha, d) ** 2)
        elif r >= d + 1:
            a0, a1 = _table(_TABLE1, alpha, d)
            inv = (a0 - a1 / r) / r
        else:
            mp = jmax / r
            inv = _basic_sum(jmax, jmax, mp, 1, alpha, d) / (jmax * _sz(0.0, 1, alpha, d) ** 2)
    elif alpha <= 0:  # case 2: unmodified, alpha <= 0
        if J <= jmax:
            Fp = m if m * (d + 1) <= jmax else np.inf
            inv = _basic_sum(J, M, S, Fp, alpha, d) / (M * _sz(0.0, Fp, alpha, d) ** 2)
        elif r >= d + 1:
            a0, a1 = _table(_TABLE2, alpha, d)
            inv = (a0 - a1 / r) / r
        else:
            mp = jmax / r
            inv = _basic_sum(jmax, jmax, mp, np.inf, alpha, d) / (jmax * _sz(0.0, np.inf, alpha, d) ** 2)
    elif alpha == 1:  # case 3: unmodified, flicker PM
        if J <= jmax:
            inv = _basic_sum(J, M, S, m, 1, d) / (M * _sz(0.0, m, 1, d) ** 2)
        else:
            b0, b1 = _TABLE3[d]
            if r >= d + 1:
                a0, a1 = _table(_TABLE2, 1, d)
                inv = (a0 - a1 / r) / ((b0 + b1 * np.log(m)) ** 2 * r)
            else:
                mp = jmax / r
                inv = _basic_sum(jmax, jmax, mp, mp, 1, d) / ((b0 + b1 * np.log(m)) ** 2 * jmax)
    else:  # case 4: unmodified, white PM: the estimator terms are correlated only at lags
        # p*m, with rho_p = (-1)^p C(2d, d+p)/C(2d, d); 1/edf = (1/M) sum_{|p| < r} (1 - |p|/r) rho_p^2,
        # which for r > d is (a0 - a1/r)/M with a0 = C(4d,2d)/C(2d,d)^2, a1 = d/2 (table 2).
        c0 = comb(2 * d, d)
        inv = 1.0
        for p in range(1, d + 1):
            if p < r:
                inv += 2.0 * (1.0 - p / r) * (comb(2 * d, d + p) / c0) ** 2
        inv /= M
    return float(1.0 / inv)


# --------------------------------------------------------------------------------------------
# noise names and the IEEE Std 952 slope readings


#: SP 1065's name of each power law (alpha of S_y(f) ~ f^alpha, the rate data's PSD), and the
#: slope mu/2 of sigma_y(tau) ~ tau^(mu/2) it gives (mu = -alpha - 1 for -2 <= alpha <= 1; white
#: and flicker PM both fall as about tau^-1; SP 1065 sec. 5.2, table 1).
NOISE_NAMES = {2: "white PM", 1: "flicker PM", 0: "white FM", -1: "flicker FM", -2: "random walk FM"}
NOISE_SLOPES = {2: -1.0, 1: -1.0, 0: -0.5, -1: 0.0, -2: 0.5}
#: The same power laws in IEEE Std 952-1997 (annex C) terms, for rate data such as a gyro's:
#: white PM is (angle) quantization noise Q, white FM the angle (velocity) random walk N, flicker
#: FM the bias instability B, random walk FM the rate random walk K.
IEEE952_NAMES = {2: "quantization (Q)", 1: "flicker PM", 0: "random walk (N)", -1: "bias instability (B)",
                 -2: "rate random walk (K)"}

#: sqrt(2 ln 2 / pi): the flat Allan deviation of flicker FM of coefficient B is B times this
#: (IEEE Std 952-1997, table C.1: sigma^2 = 2 ln 2 B^2 / pi), so B = floor / 0.664.
FLICKER_FLOOR = float(np.sqrt(2.0 * np.log(2.0) / np.pi))
# Passes of the N and K line fits, each with the other's variance removed (see ieee952_readings):
# the lines move by less than 1e-6 of themselves after the third on white noise plus a walk.
_LINE_PASSES = 4


@dataclass(frozen=True)
class SlopeReading:
    """One IEEE 952 coefficient read off an Allan deviation curve.

    Attributes:
        value: the coefficient (N and K: of the fitted line at tau_ref; B: the floor / 0.664), or
            None when the curve has no region to read it on (``reason`` says why).
        interval: (lo, hi) at the curve's confidence level, or None.
        tau_range: (first, last) tau [s] of the points it was read on, or None.
        points: number of taus read.
        reason: why ``value`` is None (None when there is a value).
    """

    value: float | None
    interval: tuple[float, float] | None
    tau_range: tuple[float, float] | None
    points: int
    reason: str | None


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) of each run of consecutive True in ``mask``."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist()))


def _line_region(r: AllanResult, alpha: int) -> tuple[slice | None, str | None]:
    """The longest run of consecutive taus identified as ``alpha`` (the first of equals), or
    None and the reason."""
    slope = NOISE_SLOPES[alpha]
    if not np.any(r.dev > 0.0):
        return None, "the deviation is 0 at every tau (constant data)"
    runs = _runs((r.alpha == alpha) & (r.dev > 0.0))     # a zero deviation has no logarithm
    if not runs:
        found = ", ".join(sorted({NOISE_NAMES[int(a)] for a in r.alpha}, key=list(NOISE_NAMES.values()).index))
        return None, f"no tau where the noise is {NOISE_NAMES[alpha]} (slope {slope:+g}); found {found}"
    a, b = max(runs, key=lambda ab: (ab[1] - ab[0], -ab[0]))
    if b - a < 2:
        return None, (f"only one tau ({r.taus[a]:.4g} s) where the noise is {NOISE_NAMES[alpha]} "
                      f"(slope {slope:+g}); a line needs two")
    return slice(a, b), None


def _line_fit(r: AllanResult, sl: slice, slope: float, other_var: np.ndarray) -> tuple[float, float]:
    """(c, sd of c) of ln sigma = c + slope ln tau on the taus ``sl``, after removing the
    variance ``other_var`` the other line puts there (at most half of each point's)."""
    nu = r.edf[sl]
    half = 0.5 * nu
    # ln(dev^) = ln(sigma) + e, dev^2 = sigma^2 chi2_nu / nu: E[e] = (psi(nu/2) - ln(nu/2)) / 2,
    # Var[e] = psi'(nu/2) / 4 (the log-gamma moments); the offset removed, weights 1/Var[e]
    bias = 0.5 * (_sps_special.digamma(half) - np.log(half))
    var = 0.25 * _sps_special.polygamma(1, half)
    w = 1.0 / var
    dev2 = r.dev[sl] ** 2
    own = np.maximum(dev2 - other_var[sl], 0.5 * dev2)
    c = float(np.sum(w * (0.5 * np.log(own) - bias - slope * np.log(r.taus[sl]))) / np.sum(w))
    # the octaves share data (their errors are positively correlated): bound the sd of the
    # weighted mean by the fully correlated case, sum(w sd) / sum(w)
    return c, float(np.sum(w * np.sqrt(var)) / np.sum(w))


def _line_readings(r: AllanResult) -> dict[str, SlopeReading]:
    """N and K: the lines of slope -1/2 and +1/2, read at 1 s and 3 s. See :func:`ieee952_readings`."""
    lines = {"N": (0, 1.0), "K": (-2, 3.0)}
    regions = {name: _line_region(r, alpha) for name, (alpha, _) in lines.items()}
    fits = {name: (0.0, 0.0) for name in lines}
    log_tau = np.log(r.taus)

    def line_var(name):  # the variance the fitted line ``name`` predicts at every tau
        if regions[name][0] is None:
            return np.zeros(r.taus.size)
        return np.exp(2.0 * (fits[name][0] + NOISE_SLOPES[lines[name][0]] * log_tau))

    for _ in range(_LINE_PASSES):
        fits = {name: _line_fit(r, regions[name][0], NOISE_SLOPES[lines[name][0]],
                                line_var("K" if name == "N" else "N")) if regions[name][0] is not None
                else fits[name] for name in lines}
    z = float(_sps.norm.ppf(0.5 * (1.0 + r.conf)))
    out = {}
    for name, (alpha, tau_ref) in lines.items():
        sl, reason = regions[name]
        if sl is None:
            out[name] = SlopeReading(None, None, None, 0, reason)
            continue
        c, sd = fits[name]
        value = float(np.exp(c + NOISE_SLOPES[alpha] * np.log(tau_ref)))
        out[name] = SlopeReading(value, (value * float(np.exp(-z * sd)), value * float(np.exp(z * sd))),
                                 (float(r.taus[sl.start]), float(r.taus[sl.stop - 1])), sl.stop - sl.start, None)
    return out


def _floor_reading(r: AllanResult) -> SlopeReading:
    """B = min dev / 0.664 where the minimum is a floor. See :func:`ieee952_readings`."""
    i = int(np.argmin(r.dev))
    n = r.dev.size
    if not r.dev[i] > 0.0:
        return SlopeReading(None, None, None, 0, f"the deviation is 0 at tau = {r.taus[i]:.4g} s (constant data "
                            "there): no flicker floor")
    rises = i < n - 1 and bool(np.any(r.lo[i + 1:] > r.hi[i]))
    if not (r.alpha[i] == -1 or (i > 0 and rises)):
        at = f"{r.taus[i]:.4g} s"
        if i == n - 1:
            why = f"the deviation is lowest at the longest tau ({at}) and has not levelled off"
        elif i == 0:
            why = f"the deviation is lowest at the shortest tau ({at}) and rises from there"
        else:
            why = (f"the minimum at {at} is not flicker FM and the deviation does not rise "
                   "significantly after it")
        return SlopeReading(None, None, None, 0, why + ": no flicker floor in this record")
    # the floor's extent: the taus around the minimum whose intervals reach down to its own
    near = r.lo <= r.hi[i]
    a, b = next((s, e) for s, e in _runs(near) if s <= i < e)
    return SlopeReading(float(r.dev[i] / FLICKER_FLOOR),
                        (float(r.lo[i] / FLICKER_FLOOR), float(r.hi[i] / FLICKER_FLOOR)),
                        (float(r.taus[a]), float(r.taus[b - 1])), b - a, None)


def ieee952_readings(r: AllanResult) -> dict[str, SlopeReading]:
    """The IEEE Std 952-1997 (annex C) slope readings of an Allan deviation of rate data: the
    coefficients as allan_variance_ros and imu_utils report them.

    * ``N`` (angle / velocity random walk, units/sqrt(Hz)): sigma = N / sqrt(tau), so N is the
      value at tau = 1 s of the line of slope -1/2;
    * ``K`` (rate random walk, units/sqrt(s)): sigma = K sqrt(tau / 3), the value at tau = 3 s of
      the line of slope +1/2;
    * ``B`` (bias instability, units): the flicker floor sigma = 0.664 B, so B = min sigma / 0.664.

    Where the slope is -1/2 (+1/2): at the taus whose identified noise type (``r.alpha``, lag-1
    autocorrelation or B1, see the module docstring) is white FM (random walk FM), the power laws
    whose deviations have that slope (SP 1065 sec. 5.2): the identification uses all the data at
    each tau, where the difference of two neighbouring points is a noisy slope. The line is
    fitted on the longest run of such consecutive taus (at least two), its slope held fixed as
    allan_variance_ros's ``get_intercept`` does (a least-squares line in log-log with the slope
    pinned; it fits tau < 10 s for N and every tau for K, here the run says where), each point
    weighted by 1 / Var(ln dev^) and its mean offset removed (dev^2 ~ sigma^2 chi2_nu / nu with
    nu = ``r.edf``: E[ln dev^] - ln sigma = (psi(nu/2) - ln(nu/2)) / 2, Var = psi'(nu/2) / 4).
    The interval bounds the fit's sd by the fully correlated case (the octaves share data) at
    the curve's confidence level ``r.conf``.

    B (as imu_utils divides by 0.6643): the minimum is read as a floor when its noise type is
    flicker FM, or when it lies after the shortest tau and some longer tau's interval lies
    wholly above the minimum's (the curve turns up); a curve still falling at its longest tau
    (white noise only) or rising from its shortest has none. ``tau_range`` is the run of taus
    around the minimum whose intervals reach down to its upper bound; the interval is the
    minimum's own.

    Readings that cannot be made are None with the reason. Only for ``adev`` and ``oadev``
    (the modified deviation has other slopes).
    """
    if r.kind not in ("adev", "oadev"):
        raise StatsError(f"r: IEEE 952 slope readings are defined on adev or oadev, not {r.kind}")
    return {**_line_readings(r), "B": _floor_reading(r)}


# --------------------------------------------------------------------------------------------
# Greenhall & Riley (2003) building blocks


def _sw(t, alpha: int):
    """sw(t) of eq. (7): the generalised autocovariance of the phase for S_y ~ f^alpha."""
    t = np.abs(np.asarray(t, dtype=np.float64))
    if alpha in (1, -1, -3):
        with np.errstate(divide="ignore", invalid="ignore"):
            lg = np.where(t > 0.0, np.log(np.where(t > 0.0, t, 1.0)), 0.0)
    if alpha == 2:
        return -t
    if alpha == 1:
        return t**2 * lg
    if alpha == 0:
        return t**3
    if alpha == -1:
        return -(t**4) * lg
    if alpha == -2:
        return -(t**5)
    if alpha == -3:
        return t**6 * lg
    return t**7  # alpha == -4


def _sx(t, F, alpha: int):
    """sx(t) of eq. (8): sw filtered by the averaging (F = inf: the limit sw_{alpha+2})."""
    if np.isinf(F):
        return _sw(t, alpha + 2)
    return F * F * (2.0 * _sw(t, alpha) - _sw(t - 1.0 / F, alpha) - _sw(t + 1.0 / F, alpha))


def _sz(t, F, alpha: int, d: int):
    """sz(t) of eq. (9): sx filtered by the d-th difference, sum_k (-1)^k C(2d, d+k) sx(t+k)."""
    t = np.asarray(t, dtype=np.float64)
    out = np.zeros_like(t)
    for k in range(-d, d + 1):
        out = out + ((-1) ** abs(k)) * comb(2 * d, d + k) * _sx(t + k, F, alpha)
    return out


def _basic_sum(J, M, S, F, alpha: int, d: int) -> float:
    """BasicSum of eq. (10): sz(0)^2 + (1 - J/M) sz(J/S)^2 + 2 sum_{j=1}^{J-1} (1 - j/M) sz(j/S)^2."""
    J = int(J)
    j = np.arange(1, J, dtype=np.float64)
    total = float(_sz(0.0, F, alpha, d)) ** 2
    total += (1.0 - J / M) * float(_sz(J / S, F, alpha, d)) ** 2
    total += 2.0 * float(np.sum((1.0 - j / M) * _sz(j / S, F, alpha, d) ** 2))
    return total


def _table(table, alpha: int, d: int) -> tuple[float, float]:
    value = table.get((alpha, d))
    if value is None:
        raise StatsError(f"alpha: no Greenhall table entry for alpha={alpha}, d={d}")
    return value


# (a0, a1) of Greenhall & Riley (2003) table 1 (modified variances) and table 2 (unmodified).
_TABLE1 = {
    (2, 1): (2 / 3, 1 / 3), (2, 2): (7 / 9, 1 / 2), (2, 3): (22 / 25, 2 / 3),
    (1, 1): (0.840, 0.345), (1, 2): (0.997, 0.616), (1, 3): (1.141, 0.843),
    (0, 1): (1.079, 0.368), (0, 2): (1.033, 0.607), (0, 3): (1.184, 0.848),
    (-1, 2): (1.048, 0.534), (-1, 3): (1.180, 0.816),
    (-2, 2): (1.302, 0.535), (-2, 3): (1.175, 0.777),
    (-3, 3): (1.194, 0.703),
    (-4, 3): (1.489, 0.702),
}  # fmt: skip
_TABLE2 = {
    (2, 1): (3 / 2, 1 / 2), (2, 2): (35 / 18, 1.0), (2, 3): (231 / 100, 3 / 2),
    (1, 1): (78.6, 25.2), (1, 2): (790.0, 410.0), (1, 3): (9950.0, 6520.0),
    (0, 1): (2 / 3, 1 / 6), (0, 2): (2 / 3, 1 / 3), (0, 3): (7 / 9, 1 / 2),
    (-1, 2): (0.852, 0.375), (-1, 3): (0.997, 0.617),
    (-2, 2): (1.079, 0.368), (-2, 3): (1.033, 0.607),
    (-3, 3): (1.053, 0.553),
    (-4, 3): (1.302, 0.535),
}  # fmt: skip
# (b0, b1) of table 3 (unmodified, alpha = 1), by d.
_TABLE3 = {1: (6.0, 4.0), 2: (15.23, 12.0), 3: (47.8, 40.0)}


# --------------------------------------------------------------------------------------------
# core


_CHUNK = 1 << 15  # elements per in-cache block for sums of products


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """sum(a * b), accumulated in float64 one cache-sized block at a time.

    einsum rather than BLAS dot, which starts threads per call and is slow under CPU
    contention; blockwise accumulation also keeps the rounding error of long sums small."""
    total = 0.0
    for start in range(0, a.size, _CHUNK):
        total += float(np.einsum("i,i->", a[start : start + _CHUNK], b[start : start + _CHUNK]))
    return total


class _Series:
    """Phase of the rate data as a cumulative sum: s[0] = 0, s[k] = sum_{i<k} (y_i - mean y),
    so the phase is x_k = s[k] / rate (plus a line, which no estimator here sees)."""

    def __init__(self, s: np.ndarray, rate: float, yc: np.ndarray | None = None):
        self.s = s
        self.rate = rate
        self.n = s.size - 1  # number of rate samples N
        self._yc = yc  # the mean-removed rate itself, when known (block means at m = 1)
        self._chunk = np.empty(_CHUNK, dtype=np.float64)

    def second_diff(self, m: int, out: np.ndarray | None = None) -> np.ndarray:
        """d_i = s[i+2m] - 2 s[i+m] + s[i], i = 0..N-2m.

        d_i / m is the difference of the two adjacent m-averages of y starting at i."""
        s = self.s
        k = s.size - 2 * m
        out = np.empty(k) if out is None else out[:k]
        np.subtract(s[2 * m :], s[m : m + k], out=out)
        out -= s[m : m + k]
        out += s[:k]
        return out

    def block_means(self, m: int) -> np.ndarray:
        """Non-overlapping m-averages of the (mean-removed) rate, floor(N/m) of them."""
        if m == 1 and self._yc is not None:
            return self._yc
        k = self.n // m
        return np.diff(self.s[: k * m + 1 : m]) / m

    def avar(self, m: int) -> tuple[float, int]:
        s = self.s[::m]
        d = s[2:] - 2.0 * s[1:-1] + s[:-2]
        return _dot(d, d) / (2.0 * m * m * d.size), int(d.size)

    def oavar(self, m: int) -> tuple[float, int]:
        # sum of squared second differences, one cache-sized chunk at a time (no N-sized
        # temporaries: memory traffic is three streaming reads of s)
        s = self.s
        k = s.size - 2 * m
        total = 0.0
        for start in range(0, k, _CHUNK):
            stop = min(k, start + _CHUNK)
            b = self._chunk[: stop - start]
            np.subtract(s[start + 2 * m : stop + 2 * m], s[start + m : stop + m], out=b)
            b -= s[start + m : stop + m]
            b += s[start:stop]
            total += float(np.einsum("i,i->", b, b))
        return total / (2.0 * m * m * k), int(k)

    def mvar(self, m: int) -> tuple[float, int]:
        d = self.second_diff(m)
        if m == 1:
            w = d
        else:
            c = np.empty(d.size + 1)
            c[0] = 0.0
            np.cumsum(d, out=c[1:])
            w = np.subtract(c[m:], c[:-m], out=d[: d.size - m + 1])  # sums of m second differences
        return _dot(w, w) / (2.0 * float(m) ** 4 * w.size), int(w.size)


def _rate_series(y, rate) -> _Series:
    rate = positive_float(rate, "rate")
    # three rate samples (four phase points) at least: m = 1 needs two adjacent means, and the
    # Greenhall edf of the second difference needs L + 1 = 4 phase points
    yy = as_series(y, "y", min_len=3)
    yc = yy - yy.mean()
    s = np.empty(yy.size + 1)
    s[0] = 0.0
    np.cumsum(yc, out=s[1:])
    return _Series(s, rate, yc)


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


def _delta_lag1(z: np.ndarray) -> float:
    """delta = r1/(1 + r1), r1 = [(1/N) sum (z_t - zbar)(z_{t+1} - zbar)] / [sample variance]."""
    n = z.size
    zbar = float(np.mean(z))
    # sum (z_t - zbar)(z_{t+1} - zbar) and sum (z_t - zbar)^2 expanded, so that no centred copy
    # is made; z here is a mean-removed rate or its differences, so zbar is ~0 and the
    # expansion loses nothing.
    num = _dot(z[:-1], z[1:]) - zbar * (2.0 * zbar * n - z[0] - z[-1]) + (n - 1) * zbar * zbar
    den = _dot(z, z) - n * zbar * zbar
    if den <= 0.0:
        return 0.0
    r1 = num / den * (n - 1) / n
    return r1 / (1.0 + r1)


def _b1_expected(N: float, mu: int) -> float:
    """Expected B1 ratio for N averages and Allan-variance tau exponent mu (Howe et al. 2000,
    table 3; SP 1065 sec. 5.6)."""
    if mu == 2:
        return N * (N + 1.0) / 6.0
    if mu == 1:
        return N / 2.0
    if mu == 0:
        return N * np.log(N) / (2.0 * (N - 1.0) * np.log(2.0))
    if mu == -1:
        return 1.0
    return (N * N - 1.0) / (1.5 * N * (N - 1.0))  # mu == -2


def _b1_mu(b1: float, N: float) -> int:
    """mu whose expected B1 is nearest (boundaries: arithmetic mean between mu = 2 and 1,
    geometric means elsewhere; Howe et al. 2000, table 4)."""
    mus = (2, 1, 0, -1, -2)
    expected = [_b1_expected(N, mu) for mu in mus]
    for i in range(len(mus) - 1):
        a, b = expected[i], expected[i + 1]
        boundary = 0.5 * (a + b) if mus[i] == 2 else np.sqrt(a * b)
        if b1 > boundary:
            return mus[i]
    return -2


def _alpha_b1(series: _Series, m: int, n_terms: int) -> int | None:
    z = series.block_means(m)
    if z.size < 3 or n_terms < 2:
        return None
    avar = 0.5 * float(np.mean(np.diff(z) ** 2))
    if avar <= 0.0:
        return None
    b1 = float(np.var(z, ddof=1)) / avar
    mu = _b1_mu(b1, float(n_terms))
    if mu == -2:  # white or flicker PM: R(n) = MVAR/AVAR (NIST TN 1337, table A-6)
        if 3 * m > series.n + 1:
            return 2
        rn = series.mvar(m)[0] / avar
        r_fpm = 3.37 / (1.04 + 3.0 * np.log(np.pi * m))
        r_wpm = 1.0 / m
        return 1 if rn > np.sqrt(r_fpm * r_wpm) else 2
    return max(-2, -mu - 1)  # mu = -alpha - 1 for -3 <= alpha <= 1; alpha < -2 clipped


def _identify_alpha(series: _Series, ms: np.ndarray, ns: np.ndarray) -> np.ndarray:
    out = np.zeros(ms.size, dtype=np.int64)
    previous = None
    for i, (m, n_terms) in enumerate(zip(ms.tolist(), ns.tolist())):
        n_avg = series.n // m
        a = None
        if n_avg >= _ACF_MIN_POINTS:
            a = noise_id_lag1(series.block_means(m), dmax=2)[0]
        elif (n_avg >= _B1_MIN_POINTS and n_terms >= _B1_MIN_TERMS) or previous is None:
            a = _alpha_b1(series, m, n_terms)
        if a is None:
            a = previous if previous is not None else 0  # nothing to go on: white FM
        a = int(min(2, max(-2, a)))
        out[i] = a
        previous = a
    return out


def _alpha_override(alpha, size: int) -> np.ndarray:
    arr = np.asarray(alpha)
    if arr.ndim == 0:
        arr = np.full(size, arr)
    if arr.shape != (size,):
        raise StatsError(f"alpha: expected an int or {size} ints (one per tau), found shape {arr.shape}")
    if not np.all(np.isin(arr, (-2, -1, 0, 1, 2))):
        raise StatsError(f"alpha: expected integers in [-2, 2], found {arr.tolist()}")
    return arr.astype(np.int64)


def _run(kind: str, series: _Series, taus, conf, alpha) -> AllanResult:
    conf = probability(conf, "conf")
    ms = _averaging_factors(kind, series.n, series.rate, taus)
    var_fn = {"adev": series.avar, "oadev": series.oavar, "mdev": series.mvar}[kind]
    var = np.empty(ms.size)
    ns = np.empty(ms.size, dtype=np.int64)
    for i, m in enumerate(ms.tolist()):
        var[i], ns[i] = var_fn(m)
    dev = np.sqrt(var)
    alphas = _identify_alpha(series, ms, ns) if alpha is None else _alpha_override(alpha, ms.size)
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
