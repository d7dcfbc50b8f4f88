"""The spread of each estimator of the comparison under the model (Gaussian), from the variogram.

The views' expectations are :mod:`noiselab.model.expected`'s (one place for every estimator's
expected value); here are their sampling distributions: the variance of a window's sample
variance (:func:`windowed_variance_var`) and its kurtosis (:func:`window_kurtosis`), the
covariance between windows (:func:`_window_covariances`), the equivalent dof of the overlapping
Allan variance (:func:`allan_edf_model`) and of a Welch band under the model's own spectrum
(:func:`psd_band_dof_factor`), and the statistics of log chi-squared ratios that standardize them.
"""

from __future__ import annotations

import numpy as np
from scipy import stats as sps
from scipy.signal import get_window
from scipy.special import digamma, polygamma

from ...memo import Memo
from ...stats.psd import window_autocorrelation


# -- statistics of log chi-squared ratios -----------------------------------------------------------------
def _log_chi2_z(emp, pred, nu):
    nu = np.asarray(nu, float)
    bias = digamma(nu / 2) - np.log(nu / 2)
    sd = np.sqrt(polygamma(1, nu / 2))
    with np.errstate(divide="ignore", invalid="ignore"):
        return (np.log(emp / pred) - bias) / sd


def _chi2_band(pred, nu, alpha):
    nu = np.asarray(nu, float)
    return pred * sps.chi2.ppf(alpha / 2, nu) / nu, pred * sps.chi2.ppf(1 - alpha / 2, nu) / nu



def _z2_var_linear(nu):
    """Var(z^2) of z = (X - 1) / sqrt(2 / nu), X ~ chi2_nu / nu: E z^4 = 3 + 12 / nu."""
    return 2.0 + 12.0 / np.asarray(nu, float)


def _z2_var_log(nu):
    """Var(z^2) of the standardized ln(chi2_nu / nu): its kurtosis is 3 + psi3(nu/2) / psi1(nu/2)^2
    (psi3, psi1: the polygamma functions of order 3 and 1)."""
    h = np.asarray(nu, float) / 2
    return 2.0 + polygamma(3, h) / polygamma(1, h) ** 2


def _tri_sums(g: np.ndarray, W: int, centres: np.ndarray) -> np.ndarray:
    """sum_{i,l < W} g(|c + l - i|) = sum_{|d| < W} (W - |d|) g(c + d) for each c in ``centres``
    (c >= W - 1, so that c + d >= 0), by prefix sums of g and m g(m)."""
    m = np.arange(g.size, dtype=float)
    P1 = np.concatenate([[0.0], np.cumsum(g)])
    P2 = np.concatenate([[0.0], np.cumsum(m * g)])
    c = np.asarray(centres, int)
    lo, mid, hi = c - W + 1, c + 1, c + W
    left = (W - c) * (P1[mid] - P1[lo]) + (P2[mid] - P2[lo])          # m = c-W+1..c: (W - c + m) g(m)
    right = (W + c) * (P1[hi] - P1[mid]) - (P2[hi] - P2[mid])         # m = c+1..c+W-1: (W + c - m) g(m)
    return left + right



def _window_covariances(gam: np.ndarray, W: int, n_win: int, var0: float, H: int = 20) -> np.ndarray:
    """Cov_h, h = 1..(up to H), between the sample variances (mean removed) of windows of W samples
    h windows apart (Gaussian): Cov = (2/W^2) ||P T P||_F^2 with T_ij = -gamma(|hW + j - i|) and P
    the centring matrix, ||P T P||^2 = ||T||^2 - ||T 1||^2/W - ||T^T 1||^2/W + (1^T T 1)^2/W^2, all
    from prefix sums (O(W) per h). The variogram form holds for the bias walk as well. Stops
    where the correlation Cov_h / var0 falls below 1e-3 or the variogram ends."""
    out = []
    for h in range(1, min(H, n_win - 1) + 1):
        D = h * W
        lo, hi = D - (W - 1), D + (W - 1)
        if hi >= gam.shape[0]:
            break
        k = np.arange(lo, hi + 1)
        Tk = -gam[np.abs(k)]                                       # T for j - i = k - D
        cnt = W - np.abs(k - D)
        tt = float(np.sum(cnt * Tk**2))
        P = np.concatenate([[0.0], np.cumsum(Tk)])                 # P[a] = sum_{k' < lo + a} Tk
        i = np.arange(W)
        u = P[(D + W - 1 - i) - lo + 1] - P[(D - i) - lo]          # row sums: j = 0..W-1
        v = P[(D + i) - lo + 1] - P[(D + i - (W - 1)) - lo]        # column sums: i = 0..W-1
        sm = float(np.sum(u))
        cc = tt - float(np.dot(u, u)) / W - float(np.dot(v, v)) / W + sm**2 / W**2
        out.append((2.0 / W**2) * max(cc, 0.0))
        if out[-1] / var0 < 1e-3:
            break
    return np.array(out)


def _window_correlation(gam: np.ndarray, W: int, n_win: int, var0: float, H: int = 20) -> float:
    """1 + 2 sum_h (1 - h/n) rho_h^2, rho_h = Cov_h / var0 the correlation between the sample
    variances of windows h apart (:func:`_window_covariances`)."""
    rho = _window_covariances(gam, W, n_win, var0, H) / var0
    h = np.arange(1, rho.size + 1)
    return float(1.0 + 2.0 * np.sum((1 - h / n_win) * rho**2))


def windowed_variance_var(gam: np.ndarray, W: int) -> float:
    """Var of the windowed sample variance (mean removed, 1/W) of a Gaussian process with
    variogram ``gam`` (rows d = 0..>=W-1): exactly (2/W^2) sum_ij C_ij^2, with C_ij = -gamma(|i-j|)
    + g(i) + g(j) - G the covariance of the demeaned window, in O(W). With g(i) = (1/W) sum_j
    gamma(|i-j|), G = mean g and h = g - G/2:
      sum_ij gamma(|i-j|)^2 = W gamma(0)^2 + 2 sum_{d>=1} (W-d) gamma(d)^2,
      sum_ij (h_i + h_j)^2 = 2 W sum h^2 + 2 (sum h)^2,
      sum_ij gamma(|i-j|) (g_i + g_j - G) = 2 W sum g^2 - W^2 G^2.
    (The stationary approximation (2/W) sum_d (1-|d|/W) R(d)^2 understates it 2.2x for a
    Gauss-Markov bias whose tau exceeds the window.)"""
    g_ = np.asarray(gam[:W], float)
    S = np.cumsum(g_)
    a = np.arange(W)
    g = (S[a] + S[W - 1 - a]) / W
    G = g.mean()
    d = np.arange(1, W)
    s_gg = W * g_[0] ** 2 + 2.0 * np.sum((W - d) * g_[1:] ** 2)
    h = g - G / 2
    s_hh = 2.0 * W * np.sum(h**2) + 2.0 * np.sum(h) ** 2
    s_gh = 2.0 * W * np.sum(g**2) - W**2 * G**2
    return float(2.0 * (s_gg + s_hh - 2.0 * s_gh) / W**2)


KURT_DENSE = 400          # windows up to this many samples: all eigenvalues (dense); longer:
KURT_TOP = 12             # ... the largest eigenvalues by Lanczos, and the rest's sum lambda^4 by
KURT_PROBES = 16          # ... Hutchinson's estimator on the deflated matrix (fixed Rademacher probes)


def window_kurtosis(gam: np.ndarray, W: int) -> float:
    """sum lambda^4 / (sum lambda^2)^2 over the eigenvalues lambda of the covariance C = P (-Gamma) P
    of a demeaned window of W samples (Gamma_ij = gamma(|i - j|), P the centring matrix). The
    windowed sample variance is the Gaussian quadratic form sum lambda_i chi2_1 / W, whose
    standardized z has E z^4 = 3 + 12 sum lambda^4 / (sum lambda^2)^2 (its cumulants are
    2^(r-1) (r-1)! sum lambda^r). The chi-squared of matching mean and variance (nu = (sum
    lambda)^2 / sum lambda^2) gives 3 + 12 / nu instead, which understates it when a few
    eigenvalues dominate: a plant or a drift slower than the window (generated case 56: 12 / nu =
    0.65 against 9.6; the view's error measured sd 0.66 over 40 records, predicted 0.23, now 0.48).
    Up to :data:`KURT_DENSE` samples from every eigenvalue. Beyond, sum lambda^2 = ||C||_F^2 exactly
    (:func:`windowed_variance_var`), the :data:`KURT_TOP` largest eigenvalues by Lanczos
    (matrix-vector products by FFT, a fixed start), and the rest's sum lambda^4 = tr(C_rest^4)
    by Hutchinson's estimator E ||C_rest^2 z||^2 over :data:`KURT_PROBES` fixed Rademacher
    probes z, C_rest = C with the top eigenpairs removed: its spectrum is flat enough for a few
    probes (within 1 % of the dense value on the seed's windows of 1000 to 2000 samples)."""
    g_ = -np.asarray(gam[:W], float)
    s2 = windowed_variance_var(gam, W) * W**2 / 2.0            # sum lambda^2 = ||C||_F^2
    if not (s2 > 0 and np.isfinite(s2)):
        return float("nan")
    if W <= KURT_DENSE:
        i = np.arange(W)
        Cm = g_[np.abs(i[:, None] - i[None, :])]
        Cm = Cm - Cm.mean(axis=0, keepdims=True)
        Cm = Cm - Cm.mean(axis=1, keepdims=True)
        lam = np.linalg.eigvalsh(Cm)
        return float(np.sum(lam**4) / np.sum(lam**2) ** 2)
    from scipy.sparse.linalg import ArpackError, LinearOperator, eigsh

    nfft = 1 << int(np.ceil(np.log2(2 * W)))
    F = np.fft.rfft(np.concatenate([g_, np.zeros(nfft - 2 * W + 1), g_[:0:-1]]))

    def mv(x):
        x = np.asarray(x, float)
        y = np.fft.irfft(F[:, None] * np.fft.rfft(x - x.mean(axis=0), nfft, axis=0), nfft, axis=0)[:W]
        return y - y.mean(axis=0)

    rng = np.random.default_rng(0)
    try:
        lam, V = eigsh(LinearOperator((W, W), matvec=lambda x: mv(np.asarray(x).reshape(W, 1))[:, 0],
                                      matmat=mv, dtype=float),
                       k=KURT_TOP, which="LA", tol=1e-5, v0=rng.standard_normal(W))
    except ArpackError:
        return float("nan")

    def rest(X):                                               # C with the top eigenpairs removed
        X = X - V @ (V.T @ X)
        Y = mv(X)
        return Y - V @ (V.T @ Y)

    Z = rng.choice([-1.0, 1.0], size=(W, KURT_PROBES))
    tail = float(np.mean(np.sum(rest(rest(Z)) ** 2, axis=0)))
    return float((np.sum(lam**4) + tail) / s2**2)



PSD_FINE = 16          # the model's spectrum for the bands' dof, resolved to 1/16 of a Welch bin
PSD_LEAK_BINS = 8      # the Hann segment's spectral window kept to +-8 bins (power beyond: < 1e-7)
PSD_DOF_MAX = 1e6      # the factor's cap: a tone over (numerically) no noise is a band known exactly


def psd_fine_length(L: int, n: int) -> int:
    """G, the lags (and half the grid) of the model's fine spectrum for segments of L samples and a
    record of n samples: L times a power of two (so that every bin sits on the grid), at most
    PSD_FINE L and at most n; 0 when that leaves less than 4 L (then the flat dof are kept: the
    R(0) V(f) term the variogram form leaves out reaches the first bin)."""
    k = int(np.floor(np.log2(max(min(PSD_FINE, n / L), 1.0))))
    return L << k if k >= 2 else 0




# |H(f)|^2 of the last few (L, G, window), shared and read-only
_HANN_POWER = Memo(4, lru=True)


def _hann_power_on_grid(L: int, G: int, window: str) -> np.ndarray:
    """|H(f)|^2 of the L-sample window at f = k / (2 G), k = 0..PSD_LEAK_BINS * 2G / L."""
    def compute():
        w = get_window(window, L)
        s = 2 * G // L
        out = np.abs(np.fft.rfft(w, 2 * G)[: PSD_LEAK_BINS * s + 1]) ** 2
        out.setflags(write=False)                      # shared by every caller (threads included)
        return out
    return _HANN_POWER.get_or_compute((L, G, window), compute)


def _fine_spectrum(g: np.ndarray, G: int) -> np.ndarray:
    """The spectrum (arbitrary units) at f = k / (2 G) cycles/sample, k = 0..G, of a process with
    variogram ``g`` (rows >= G), smoothed by the lag window of a G-sample Hann taper (whose
    transform is >= 0): S(f) = -sum_{|d|<G} gamma(|d|) v(d) cos(2 pi f d). The R(0) V(f) term the
    variogram form leaves out lives below 2 / G, under the first Welch bin (at least 4 / G)."""
    cw = window_autocorrelation(get_window("hann", G))
    a = g[:G] * (cw / cw[0])
    return np.maximum(-2.0 * np.fft.rfft(a, 2 * G).real, 0.0)


def psd_band_dof_factor(gam_total: np.ndarray, gam_lines: np.ndarray | None, L: int, groups, G: int,
                        window: str = "hann") -> np.ndarray:
    """Factor on each band's equivalent dof of the Welch mean under the model's spectrum S.

    The flat dof nu_flat (:func:`noiselab.stats.psd._average_groups`) holds for a spectrum flat
    across the band's spectral window W_b (the mean over the band's bins of the segment window's
    |H(f - f_j)|^2). A resonance narrower than a bin (half-power width 2 zeta f_n < 1 / (L Ts)) is
    not flat there: its correlation time is longer than a segment, the segments and bins are not
    independent and the flat dof overstate what the band knows. With S smooth at the record's resolution (Priestley 1981, 6.2.4),
    E = int S W_b and Var is proportional to int S^2 W_b^2, so
    nu = nu_flat (E / int W_b)^2 / (int (S_n^2 + 2 S_n S_l) W_b^2 / int W_b^2),
    which is nu_flat for a flat S. S_l: the spectral lines (``gam_lines``, the tones; S_n the rest),
    whose power in a band is the same in every segment (random phase, fixed amplitude): they add
    to E and, through their product with the noise, 2 S_n S_l to the variance, but no variance of
    their own; except in a band whose window reaches DC or Nyquist, where a line's power depends
    on its phase (its mirror image), and it counts as noise. The factor is capped at PSD_DOF_MAX.
    S is resolved to 1 / PSD_FINE of a bin (as far as the record allows: G from
    :func:`psd_fine_length`; G = 0 keeps the flat dof). Returns nu / nu_flat."""
    if G < 4 * L or gam_total.shape[0] < G:
        return np.ones(len(groups))
    s = 2 * G // L                                     # grid points per Welch bin (exact: G = L 2^k)
    lines = gam_lines is not None
    Sn = _fine_spectrum(gam_total - gam_lines if lines else gam_total, G)
    Sl = _fine_spectrum(gam_lines, G) if lines else np.zeros_like(Sn)
    Sn[: s // 2] = Sn[s // 2]                          # below half a bin: the mean removal's job
    Sl[: s // 2] = Sl[s // 2]
    S = Sn + Sl
    V = Sn**2 + 2.0 * Sn * Sl                          # the lines' own variance left out ...
    V_edge = S**2                                      # ... but where their mirror image reaches
    H2 = _hann_power_on_grid(L, G, window)
    off = np.arange(-(H2.size - 1), H2.size)
    ker = H2[np.abs(off)]
    fac = np.ones(len(groups))
    for b, gr in enumerate(groups):
        idx = (gr[:, None] * s + off[None, :]).ravel()
        edge = bool(idx.min() < 0 or idx.max() > G)
        idx = np.abs(idx)                              # fold at 0 and at Nyquist (S is even)
        idx = np.where(idx > G, 2 * G - idx, idx)
        Wb = np.bincount(idx, weights=np.tile(ker, gr.size), minlength=G + 1)
        sel = np.flatnonzero(Wb)
        W = Wb[sel]
        E = np.dot(S[sel], W) / W.sum()
        var = np.dot((V_edge if edge else V)[sel], W**2) / np.dot(W, W)
        if E > 0:
            fac[b] = min(E**2 / var, PSD_DOF_MAX) if var > 0 else PSD_DOF_MAX
    return fac



def allan_edf_model(gam: np.ndarray, m: np.ndarray, n: int, corr: int) -> np.ndarray:
    """Equivalent dof of the overlapping Allan variance estimator *under the model* (Gaussian):
    z_k = (ybar_{k+m} - ybar_k)/sqrt(2) has Cov_z(d) = -(1/(2 m^2)) sum_e c_m(|e|) gamma(|e - d|)
    (c_m the Allan filter's autocorrelation), Var(AVAR^) = (2/Na) sum_{|d|<Na} (1 - |d|/Na) Cov_z(d)^2,
    nu = 2 AVAR^2 / Var. Cov_z vanishes beyond 2m + (the stationary part's correlation length
    ``corr``), where the sum is cut. ``gam`` (L, ) variogram with L >= n."""
    from scipy.signal import fftconvolve

    nu = np.empty(m.size)
    for i, mm in enumerate(m):
        mm = int(mm)
        Na = n - 2 * mm + 1
        D = int(min(Na - 1, 2 * mm + corr))
        e = np.arange(-(2 * mm - 1), 2 * mm)
        ae = np.abs(e)
        c = np.where(ae <= mm, 2 * mm - 3 * ae, -(2 * mm - ae)).astype(float)
        lags = np.abs(np.arange(-(2 * mm - 1), D + 2 * mm))     # |e - d| for the needed range
        g = gam[np.minimum(lags, gam.shape[0] - 1)]
        cov = -fftconvolve(g, c[::-1], mode="valid")[: D + 1] / (2.0 * mm**2)
        d = np.arange(D + 1)
        w = np.where(d == 0, 1.0, 2.0) * (1 - d / Na)
        var = 2.0 / Na * np.sum(w * cov**2)
        nu[i] = 2 * cov[0] ** 2 / var
    return nu


def allan_z(avar_emp, avar_pred, nu):
    """Linear standardization (AVAR^ - AVAR) / sd, sd = AVAR sqrt(2 / nu): E[z^2] = 1 exactly under
    the (Gaussian) model even when nu is small and the estimate skewed."""
    return (avar_emp - avar_pred) / (avar_pred * np.sqrt(2.0 / nu))
