"""The comparison's five views of a residual against the model: each its estimate on the record,
the expectation of that very estimator under the model (:mod:`noiselab.model.expected`), its spread
(:mod:`.spread`), standardized deviations z and the view's error (formulas in :mod:`noiselab.diagnose.compare`).

``variance`` (time windows), ``level`` (the windows' means, for a record from rest), ``acf``
(lags), ``psd`` (log frequency bands) and ``allan`` (octave taus). ``mod`` (:class:`.modulation.LocalVariance`):
a white part whose variance follows the slope; ``qmod``: a quantizer's variance over its mean at
each sample (both widen the spreads); ``jkey``: what else the cached predictions depend on.
"""

from __future__ import annotations

import numpy as np
from scipy import stats as sps

from ...model.expected import expected_welch_detrended, expected_window_stats
from ...model.spectra import allan_from_variogram
from ...stats import oadev, welch
from ...stats.psd import log_bin_groups
from ..results import AnalysisError, View
from .cache import _cached
from .modulation import modulation_kappa
from .spread import (
    _chi2_band,
    _log_chi2_z,
    _tri_sums,
    _window_correlation,
    _window_covariances,
    _z2_var_linear,
    _z2_var_log,
    allan_edf_model,
    allan_z,
    psd_band_dof_factor,
    psd_fine_length,
    window_kurtosis,
    windowed_variance_var,
)

FAMILY_ALPHA = 0.05


def _finish(view: View, n_points: int, by_band: bool = False, z2_var=None, error_var=None) -> View:
    """Flag points outside the band (family-wise 5 % per view) and set the view's error. With
    ``by_band`` the (skewed) chi-squared band decides the flags, the linear z only the error.
    ``z2_var`` (per point, Var(z^2) under the model, points taken as independent) or ``error_var``
    give the variance of the view's error under the model, which weighs it in the model error."""
    zc = sps.norm.ppf(1 - FAMILY_ALPHA / (2 * max(n_points, 1)))
    view.flagged = ((view.empirical < view.lo) | (view.empirical > view.hi)) if by_band else np.abs(view.z) > zc
    view.error = float(np.mean(view.z**2)) if view.z.size else float("nan")
    view.conf = 1 - FAMILY_ALPHA / max(n_points, 1)
    if error_var is None:
        z2_var = np.broadcast_to(2.0 if z2_var is None else z2_var, view.z.shape)
        error_var = float(np.sum(z2_var)) / max(view.z.size, 1) ** 2
    view.error_var = float(error_var)
    return view



# -- the four views ------------------------------------------------------------------------------------
def variance_view(r, t, gam_parts, j, W, model=None, gam_long=None, mod=None, jkey=None, qmod=None, qk4=None):
    """Variances over windows of W samples against their expectation. ``mod``: the jitter's
    modulation (its part follows the slope); ``qmod`` (n,): a quantizer's, Var(y_k) over its mean
    (the measurement's variance follows where the mean sits between the levels, ~0 on a level and
    Delta^2 / 4 on a threshold half-way between two: each window's
    expectation scaled by its mean of ``qmod``, its spread by its mean of qmod^2 as well);
    ``qk4`` (n,): the measurement's
    excess fourth moment at each sample (a few levels are not Gaussian), sum / W^2 added to each
    window's variance of the estimate."""
    n_win = r.size // W
    if n_win < 2:
        raise AnalysisError(f"record too short for the variance window of {W} samples")
    seg = r[: n_win * W].reshape(n_win, W)
    emp = seg.var(axis=1)
    centres = t[: n_win * W].reshape(n_win, W).mean(axis=1)

    def predict():
        parts = {eid: expected_window_stats(g[:, j:j + 1], W, W - 1)[:, 0] for eid, g in gam_parts.items()}
        R = sum(parts.values())                       # expected autocovariance within a window
        gsum = sum(g[:W, j] for g in gam_parts.values())
        var = windowed_variance_var(gsum, W)
        inflate = _window_correlation(gam_long, W, n_win, var) if gam_long is not None else 1.0
        kurt = window_kurtosis(gsum, W)
        return {eid: p[:1].copy() for eid, p in parts.items()}, R[0], var, inflate, kurt   # what the view uses
    parts, E, var, inflate, kurt = predict() if model is None else \
        _cached(model, "variance_view", (j, W, n_win, gam_long is not None, jkey), predict)
    nu = np.full(n_win, 2 * E**2 / var)
    contrib = {eid: np.full(n_win, p[0]) for eid, p in parts.items()}
    scale = np.ones(n_win)
    if mod is not None and mod.share(contrib) is not None:
        # the jitter's power follows the slope: each window's expectation (and spread) with it
        local = mod.m[: n_win * W].reshape(n_win, W).mean(axis=1)
        for eid in mod.ids:
            if eid in contrib:
                contrib[eid] = contrib[eid] * local
        scale = sum(contrib.values()) / E
    spread = np.ones(n_win)
    if qmod is not None:
        qw = qmod[: n_win * W].reshape(n_win, W)
        scale = scale * qw.mean(axis=1)
        # sum_k Var(r_k^2) = sum_k 2 v_k^2 (+ k4_k): v_k unequal within a window weigh more than
        # their mean squared (a variance ~0 while the mean sits on a level, Delta^2 / 4 while it
        # sits on a decision threshold half-way between two)
        spread = np.mean(qw**2, axis=1) / np.mean(qw, axis=1) ** 2
    pred = E * scale
    est_var = var * scale**2 * spread
    if qk4 is not None:
        # + sum_k k4_k / W^2, kept to at least a tenth of the Gaussian part (k4 >= -2 Var^2)
        est_var = np.maximum(est_var + qk4[: n_win * W].reshape(n_win, W).sum(axis=1) / W**2, 0.1 * est_var)
    if qmod is not None or qk4 is not None:
        nu = 2 * pred**2 / est_var
    alpha = FAMILY_ALPHA / n_win
    lo, hi = _chi2_band(pred, nu, alpha)
    v = View("variance", j, centres, "time [s]", "variance of y in the window [units^2]", emp, pred, lo, hi,
             contributions=contrib,
             z=(emp - pred) / np.sqrt(est_var), notes=[f"windows of {W} samples, mean removed"])
    # Var(z^2) = E z^4 - 1 = 2 + 12 sum lambda^4 / (sum lambda^2)^2 (:func:`window_kurtosis`; the
    # chi-squared's 2 + 12 / nu when that is not finite)
    z2_var = 2.0 + 12.0 * kurt if np.isfinite(kurt) else _z2_var_linear(nu[0])
    return _finish(v, n_win, by_band=True, error_var=float(z2_var) / n_win * inflate)



def level_view(r, t, gam_parts, j, W, start: int, var_stat: float, walk0: float, walk_q: float, model=None,
               jkey=None):
    """The residual's mean over the variance view's windows against its prediction, 0: the mean
    response's error (a steady-state level that a saturation, a dead zone or a scale factor
    changes under a step) that every other view removes with the windows' and segments' means.
    Only for a record from rest, whose absolute level the model predicts. ``gam_parts``: the
    stationary parts' variograms (the walks are ``walk0`` = Var(b_0) and ``walk_q`` = Q per sample).

    Var of a window mean = s - E[window variance] for the stationary parts (s their variance,
    :func:`expected_window_stats`) plus, for the bias walk from b_0, Var(b_0) + Q (k_0 + c_W)
    (k_0 the window's first sample counted from the record's start, c_W = (W - 1)(2W - 1) / 6W);
    windows h apart covary by s - (1 / W^2) sum_{|d|<W} (W - |d|) gamma(hW + d) and, the walk,
    Var(b_0) + Q (k_a + (W - 1) / 2). z = mean / sd is N(0, 1) under the model; the view's error
    variance is 2 sum rho_ab^2 / n^2 over the windows' correlations (a slow bias moves every
    window's mean together: the view then weighs little in the model error)."""
    n_win = r.size // W
    if n_win < 2:
        raise AnalysisError(f"record too short for the level window of {W} samples")
    emp = r[: n_win * W].reshape(n_win, W).mean(axis=1)
    centres = t[: n_win * W].reshape(n_win, W).mean(axis=1)

    def predict():
        stat = {e: g[:, j] for e, g in gam_parts.items()}
        g_stat = sum(stat.values()) if stat else np.zeros(n_win * W + 1)
        e_win = float(expected_window_stats(g_stat[:, None], W, 0)[0, 0]) if stat else 0.0
        k0 = start + W * np.arange(n_win)
        c_w = (W - 1) * (2 * W - 1) / (6.0 * W)
        var = (var_stat - e_win) + walk0 + walk_q * (k0 + c_w)
        from scipy.linalg import toeplitz
        cov_h = var_stat - _tri_sums(g_stat, W, np.arange(1, n_win) * W) / W**2
        # stationary part by window distance; the walk's by the earlier window's first sample
        C = toeplitz(np.concatenate([[var_stat - e_win], cov_h])) + walk0 + \
            walk_q * (np.minimum.outer(k0, k0) + (W - 1) / 2.0)
        np.fill_diagonal(C, var)
        sd = np.sqrt(np.maximum(var, 1e-300))
        rho = C / np.outer(sd, sd)
        return sd, 2.0 * float(np.sum(rho**2)) / n_win**2
    sd, err_var = predict() if model is None else \
        _cached(model, "level_view", (j, W, n_win, start, jkey), predict)
    zc = sps.norm.ppf(1 - FAMILY_ALPHA / (2 * n_win))
    v = View("level", j, centres, "time [s]", "mean of y - E[y] in the window [units]", emp, np.zeros(n_win),
             -zc * sd, zc * sd, z=emp / sd,
             notes=[f"windows of {W} samples; the record's absolute level (it starts at rest)"])
    return _finish(v, n_win, error_var=err_var)



def acf_view(r, Ts, gam_parts, j, M, max_lag, model=None, gam_long=None, jkey=None, mod=None, qmod=None):
    K = r.size // M
    if K < 1:
        raise AnalysisError(f"record too short for the autocorrelation segment of {M} samples")
    seg = r[: K * M].reshape(K, M)
    seg = seg - seg.mean(axis=1, keepdims=True)
    F = np.fft.rfft(seg, 2 * M, axis=1)
    ac = np.fft.irfft(np.abs(F) ** 2, 2 * M, axis=1)[:, : max_lag + 1] / M
    emp = ac.mean(axis=0)

    def predict():
        parts = {eid: expected_window_stats(g[:, j:j + 1], M, M - 1)[:, 0] for eid, g in gam_parts.items()}
        R = sum(parts.values())
        # Bartlett: Var(r(d)) ~ (1/M) sum_k [R(k)^2 + R(k+d) R(k-d)], |k| < M, per segment, / K
        Rs = np.concatenate([R[:0:-1], R])            # R(-(M-1)) .. R(M-1)
        c = M - 1
        var = np.empty(max_lag + 1)
        for d in range(max_lag + 1):
            k = np.arange(-(M - 1), M)
            plus = k + d
            minus = k - d
            ok = (np.abs(plus) < M) & (np.abs(minus) < M)
            var[d] = (np.sum(R[np.abs(k)] ** 2) + np.sum(Rs[c + plus[ok]] * Rs[c + minus[ok]])) / M / K
        # Bartlett's formula is asymptotic: for a memory as long as the segment (a Gauss-Markov
        # bias) it misses the demeaning's effect within a segment and the correlation between
        # segments. At lag 0 the estimate is the mean of the segments' variances, whose variance is
        # exact (windowed_variance_var and _window_covariances); every lag's is scaled by that ratio
        # (lags up to M/8: the long memory that makes it differ from 1 is alike across them).
        # (gam_long: the variogram to the record's length, so every pair of segments is covered
        # and the result depends only on the cache key, whatever length gam_parts was cut to)
        gsum = sum(g[:, j] for g in gam_parts.values()) if gam_long is None else gam_long
        v0 = windowed_variance_var(gsum, M)
        cov = _window_covariances(gsum, M, K, v0, H=K - 1)          # empty for one segment
        hh = np.arange(1, cov.size + 1)
        exact0 = (v0 + 2.0 * np.sum((1 - hh / K) * cov)) / K
        if var[0] > 0 and exact0 > 0:
            var *= exact0 / var[0]
        # the estimates at nearby lags are correlated, ~ C(h) / C(0) with C(h) = sum_k R(k) R(k + h)
        # (Bartlett's leading term): Var(mean z^2) = (2 / n^2) sum_h (n - |h|) rho(h)^2
        n = max_lag + 1
        Fr = np.fft.rfft(Rs, 2 * Rs.size)
        C = np.fft.irfft(np.abs(Fr) ** 2, 2 * Rs.size)[:n]
        rho = C / C[0] if C[0] > 0 else np.zeros(n)
        h = np.arange(1, n)
        err_var = 2.0 / n**2 * (n + 2 * np.sum((n - h) * rho[1:] ** 2))
        return ({eid: p[: max_lag + 1].copy() for eid, p in parts.items()}, R[: max_lag + 1].copy(), var,
                float(err_var))                       # what the view uses
    parts, R, var, err_var = predict() if model is None else _cached(model, "acf_view", (j, M, max_lag, K, jkey), predict)
    if mod is not None and mod.share(parts) is not None:
        # Bartlett's J^2 terms (J: the jitter's variance; 2 J^2 at lag 0, J^2 beyond) take the
        # local variances' mean square, J^2 mean(m_k^2), when the jitter's power follows the slope
        J = float(mod.share(parts)[0])
        extra = (float(np.mean(mod.m**2)) / float(np.mean(mod.m)) ** 2 - 1.0) * J**2 / (M * K)
        var = var + extra * np.where(np.arange(var.size) == 0, 2.0, 1.0)
    if qmod is not None:
        # a quantizer's local variance (all of it) follows the mean's place between the levels
        # (``qmod``: Var(y_k) over its mean; see :func:`variance_view`), and can change from one
        # sample to the next (large only while the mean crosses a level): Bartlett's V^2 / n at lag
        # h takes mean(q_k q_{k+h}) / mean(q)^2, at lag 0 twice that of mean(q_k^2)
        V = float(R[0])
        q = qmod / np.mean(qmod)
        H = var.size
        qq = np.array([np.mean(q[: q.size - h] * q[h:]) for h in range(H)])
        var = var + (qq - 1.0) * V**2 / (M * K) * np.where(np.arange(H) == 0, 2.0, 1.0)
    se = np.sqrt(var)
    pred = R[: max_lag + 1]
    z = (emp - pred) / se
    zc = sps.norm.ppf(1 - FAMILY_ALPHA / (2 * (max_lag + 1)))
    v = View("acf", j, np.arange(max_lag + 1) * Ts, "lag [s]", "autocovariance [units^2]", emp, pred,
             pred - zc * se, pred + zc * se,
             contributions={eid: p[: max_lag + 1] for eid, p in parts.items()}, z=z,
             notes=[f"{K} segments of {M} samples, mean removed"])
    return _finish(v, max_lag + 1, error_var=err_var)



def psd_view(r, Ts, gam_parts, j, L, bpd, model=None, mod=None, jkey=None, gam_fine=None, line_ids=(), qmod=None):
    """The PSD view. ``gam_fine``: {id: variogram} to a length beyond the segment (the record's), for
    the bands' dof under the model's spectrum (:func:`psd_band_dof_factor`); ``line_ids``: the tones."""
    if r.size < L:
        raise AnalysisError(f"record too short for Welch segments of {L} samples")
    est = welch(r, 1.0 / Ts, nperseg=L)
    groups = log_bin_groups(est.f, bpd)
    from ...stats.psd import _average_groups
    binned = _average_groups(est, groups)
    G = 0 if gam_fine is None else psd_fine_length(L, r.size)

    def predict():
        parts = {}
        for eid, g in gam_parts.items():
            e = expected_welch_detrended(g[:, j:j + 1], L, Ts)[:, 0]
            parts[eid] = np.array([e[gr].mean() for gr in groups])
        fac = np.ones(len(groups))
        if gam_fine is not None:
            tot = sum(g[:G, j] for g in gam_fine.values())
            lines = [g[:G, j] for eid, g in gam_fine.items() if eid in line_ids]
            fac = psd_band_dof_factor(tot, sum(lines) if lines else None, L, groups, G)
        return parts, fac
    parts, fac = predict() if model is None else _cached(model, "psd_view", (j, L, bpd, jkey, G), predict)
    parts = dict(parts)
    nu = binned.dof * fac
    pred = sum(parts.values())
    notes = [f"Welch, Hann, {L}-sample segments, 50 % overlap, {bpd} bands per decade"]
    if np.any(fac < 0.9):
        b = int(np.argmin(fac))
        notes.append(f"dof under the model's spectrum: down to {fac[b]:.2g} of the flat "
                     f"value at {binned.f[b]:.3g} Hz (a spectrum that is not flat across the band)")
    if mod is not None and mod.share(parts) is not None:
        kappa = modulation_kappa(mod.m, [max(int(round(0.514 * L / len(gr))), 1) for gr in groups],
                                 mod.share(parts) / np.maximum(pred, 1e-300))
        nu = nu / kappa
        notes.append(f"dof divided by up to {kappa.max():.3g} for the jitter's modulation")
    if qmod is not None:
        kappa = modulation_kappa(qmod, [max(int(round(0.514 * L / len(gr))), 1) for gr in groups], np.ones(len(groups)))
        nu = nu / kappa
        notes.append(f"dof divided by up to {kappa.max():.3g}: the quantizer's variance follows the mean's "
                     "place between the levels")
    alpha = FAMILY_ALPHA / pred.size
    lo, hi = _chi2_band(pred, nu, alpha)
    df = float(est.f[1] - est.f[0])
    v = View("psd", j, binned.f, "frequency [Hz]", "PSD [units^2/Hz]", binned.psd, pred, lo, hi,
             contributions=parts, z=_log_chi2_z(binned.psd, pred, nu), log_x=True, log_y=True,
             notes=notes, x_lo=np.array([max(est.f[g[0]] - df / 2, 0.0) for g in groups]),
             x_hi=np.array([min(est.f[g[-1]] + df / 2, est.f[-1]) for g in groups]))
    return _finish(v, pred.size, z2_var=_z2_var_log(nu))



def allan_view(r, Ts, gam_parts_full, j, corr, model=None, mod=None, jkey=None, qmod=None):
    res = oadev(r, 1.0 / Ts, taus="octave")
    m = res.m.astype(np.int64)
    parts = {eid: allan_from_variogram(g[:, j:j + 1], m)[:, 0] for eid, g in gam_parts_full.items()}
    avar = sum(parts.values())
    total_gam = sum(g[:, j] for g in gam_parts_full.values())
    nu = allan_edf_model(total_gam, m, r.size, corr) if model is None else \
        _cached(model, "allan_edf", (j, tuple(m), r.size, corr, jkey), lambda: allan_edf_model(total_gam, m, r.size, corr))
    if mod is not None and mod.share(parts) is not None:
        nu = nu / modulation_kappa(mod.m, 2 * m, mod.share(parts) / np.maximum(avar, 1e-300))
    if qmod is not None:
        nu = nu / modulation_kappa(qmod, 2 * m, np.ones(m.size))
    alpha = FAMILY_ALPHA / m.size
    lo2, hi2 = _chi2_band(avar, nu, alpha)
    v = View("allan", j, res.taus, "tau [s]", "Allan deviation [units]", res.dev, np.sqrt(avar),
             np.sqrt(lo2), np.sqrt(hi2), contributions={eid: np.sqrt(np.maximum(a, 0)) for eid, a in parts.items()},
             z=allan_z(res.dev**2, avar, nu), log_x=True, log_y=True,
             notes=["overlapping Allan deviation, octave taus; band from the estimator's dof under the "
                    "model (not Greenhall's power-law edf: the residual is rarely a pure power law); "
                    "contributions are each effect's own deviation line (they add in variance)"])
    # neighbouring octaves share data (the overlapping estimator at 2 tau re-uses the averages at
    # tau): correlation ~0.6 between adjacent octaves, rho^2 ~ 0.36 decaying geometrically,
    # inflates Var(mean z^2) by 1 + 2 sum_h (1 - h/n) 0.36^h (Monte Carlo, 20 records of two
    # second-order plants: measured sd 0.53-0.68 against 0.41 without the factor)
    n = max(m.size, 1)
    h = np.arange(1, n)
    inflate = 1 + 2 * np.sum((1 - h / n) * 0.36**h)
    return _finish(v, m.size, by_band=True, error_var=float(np.sum(_z2_var_linear(nu))) / n**2 * inflate)
