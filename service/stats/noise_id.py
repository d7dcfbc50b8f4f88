"""Power-law noise identification of rate data at an averaging factor m, as Stable32 does it:
the noise type ``alpha`` (S_y(f) ~ f^alpha) that sets the Allan deviations' degrees of freedom.

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

References:
    NIST SP 1065: W. J. Riley, Handbook of Frequency Stability Analysis, 2008.
    W. J. Riley and C. A. Greenhall, "Power law noise identification using the lag 1
    autocorrelation", Proc. 18th EFTF, 2004.
    D. A. Howe, R. L. Beard, C. A. Greenhall, W. J. Riley, "A total estimator of the Hadamard
    function used for GPS operations", Proc. 32nd PTTI, 2000 (B1 tables).
"""

from __future__ import annotations

import numpy as np

from .allan_sums import PhaseSums, dot
from .errors import StatsError, as_series

__all__ = ["alpha_override", "identify_alpha", "noise_id_lag1"]

_ACF_MIN_POINTS = 30  # lag-1 ACF needs >= 30 averages (Riley & Greenhall 2004)
_B1_MIN_POINTS = 7  # fewer averages: Stable32 carries the previous tau's noise type forward
_B1_MIN_TERMS = 10  # fewer terms in the statistic: likewise (inferred, see module docstring)


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


def _delta_lag1(z: np.ndarray) -> float:
    """delta = r1/(1 + r1), r1 = [(1/N) sum (z_t - zbar)(z_{t+1} - zbar)] / [sample variance]."""
    n = z.size
    zbar = float(np.mean(z))
    # sum (z_t - zbar)(z_{t+1} - zbar) and sum (z_t - zbar)^2 expanded, so that no centred copy
    # is made; z here is a mean-removed rate or its differences, so zbar is ~0 and the
    # expansion loses nothing.
    num = dot(z[:-1], z[1:]) - zbar * (2.0 * zbar * n - z[0] - z[-1]) + (n - 1) * zbar * zbar
    den = dot(z, z) - n * zbar * zbar
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


def _alpha_b1(series: PhaseSums, m: int, n_terms: int) -> int | None:
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


def identify_alpha(series: PhaseSums, ms: np.ndarray, ns: np.ndarray) -> np.ndarray:
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


def alpha_override(alpha, size: int) -> np.ndarray:
    arr = np.asarray(alpha)
    if arr.ndim == 0:
        arr = np.full(size, arr)
    if arr.shape != (size,):
        raise StatsError(f"alpha: expected an int or {size} ints (one per tau), found shape {arr.shape}")
    if not np.all(np.isin(arr, (-2, -1, 0, 1, 2))):
        raise StatsError(f"alpha: expected integers in [-2, 2], found {arr.tolist()}")
    return arr.astype(np.int64)
