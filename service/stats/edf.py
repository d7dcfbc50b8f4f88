"""Confidence of a finite-difference stability variance (Allan, modified Allan, Hadamard): its
equivalent degrees of freedom and the chi-squared interval from them.

edf: the algorithm of Greenhall & Riley (2003), section 5, the one Stable32 uses
(:func:`edf_greenhall`). Interval: SP 1065 eq. (45), dev * sqrt(edf / chi2.ppf((1 +/- conf)/2,
edf)). The default ``conf = 0.683`` is Stable32's "Confidence Factor = 0.683".

References:
    NIST SP 1065: W. J. Riley, Handbook of Frequency Stability Analysis, 2008.
    C. A. Greenhall and W. J. Riley, "Uncertainty of stability variances based on finite
    differences", Proc. 35th PTTI, 2003 (equation and table numbers below as cited by the
    allantools reference implementation, which this one matches to 1e-12).
"""

from __future__ import annotations

from math import comb

import numpy as np
from scipy import stats as _sps

from .errors import StatsError, probability

__all__ = ["ONE_SIGMA_CONF", "chi2_bounds", "edf_greenhall"]

#: Stable32's default "Confidence Factor" (a one-sigma interval).
ONE_SIGMA_CONF = 0.683


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
