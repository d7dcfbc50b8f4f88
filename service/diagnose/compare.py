"""Compare a recording with a model: residual, four views, the model error, where it fails.

Residual: r_k = y_k - E[y_k], the measurement minus the model's predicted mean response to the
*recorded* command (seed section 3), so a recording that holds the command needs no truth.

Every prediction is the expectation of the very estimator applied to the data, computed exactly
from the model's per-effect variogram gamma(d) = E[(r_{k+d} - r_k)^2] / 2. For any process with
stationary increments (the linear part, tones, white noises and the bias walk alike) and any
estimator that is a quadratic form x^T A x with A annihilating constants (every estimator below
removes a mean), E[x^T A x] = -sum_{i,j} A_ij gamma(|i - j|). So the bias walk and the per-segment
mean removal are inside the predictions instead of being excluded:

* ``variance``: sample variance (mean removed) of consecutive windows of W samples (time windows);
  E = (1/W^2) sum_{i,j} gamma(|i-j|).
* ``acf``: autocovariance averaged over segments of M samples, each with its mean removed (lags);
  E[r(d)] = (1/M) [(M - d)(-gamma(d) - G) + sum_{n<M-d} (g(n) + g(n+d))], g(a) = (1/M) sum_m
  gamma(|a - m|), G = mean(g).
* ``psd``: Welch (Hann, 50 % overlap, segment mean removed, one-sided, every bin doubled as
  :func:`service.stats.welch`), averaged in log bands (frequency bands); per bin
  E|X_j|^2 = -sum_{n,m} h_n conj(h_m) gamma(|n-m|), h_n = w_n e^{-i w_j n} - W_j / L.
* ``allan``: overlapping Allan deviation at octave taus (taus), the exact discrete Allan variance
  of the model (:func:`service.model.spectra.allan_from_variogram`), its bounds from the
  estimator's equivalent degrees of freedom (Greenhall).

Standardized deviations z (E[z^2] = 1 when the model is right):
  psd (log bands, nu in the tens to thousands): z = (ln(emp / pred) - E[ln(chi2_nu / nu)]) /
  sd[ln(chi2_nu / nu)], E = digamma(nu/2) - ln(nu/2), Var = trigamma(nu/2), nu the equivalent dof;
  variance and allan (few dof at long windows and taus, skewed estimates): z = (emp - pred) / sd
  with the estimator's exact variance under the Gaussian model, so E[z^2] = 1 holds exactly; their
  flags come from the chi-squared band with nu = 2 E^2 / Var;
  acf: z = (emp - pred) / se, se from Bartlett's formula with the predicted autocovariance,
  divided by the number of segments, then scaled to the exact variance at lag 0 (the mean of the
  segments' variances, the correlation between segments included): Bartlett alone understates it
  when a memory (a Gauss-Markov bias) is as long as the segment.
The error of a view is mean(z^2); **the model error** is the mean of the views' errors (outputs
averaged). Both are about 1 when the model explains the data within the sampling noise of the
estimators and grow with the mismatch (a factor f in power in a band adds about (ln f)^2 nu / 2).
Points with |z| beyond the Bonferroni threshold of their view (family-wise 5 %) are flagged;
contiguous flagged runs are the :class:`Region` s where the data leave the model.

A jitter (sensor.jitter) is white noise whose variance follows the slope, std_s^2 ydot_k^2: its level
is taken over the analysed record's own mean response, and the estimators' spreads are widened for
the modulation (:func:`modulation_kappa`; the variance view predicts each window's own level).

A quantizer's error is correlated when the signal crosses few steps per sample; how much depends
on the other sources and on the mean response's increments over the record
(:func:`quantization_gamma`, :mod:`service.model.effects.sensor_quantization`).

The analysis starts after the model's transient from rest when the recording starts at rest
(``burn``): noiselab's emulator starts every state at zero, and the predictions are stationary.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import replace
from functools import lru_cache

import numpy as np
from scipy import stats as sps
from scipy.signal import get_window
from scipy.special import digamma, polygamma

from .. import parallel
from ..model import ModelError
from ..model.expected import (
    _welch_kernel,
    expected_welch_detrended,
    expected_window_stats,
)
from ..model.lyapunov import LEAK
from ..model.mean_response import free_response_fit
from ..model.spectra import allan_from_variogram
from ..stats import oadev, welch
from ..stats.psd import log_bin_groups, window_autocorrelation
from .results import VIEW_NAMES, AnalysisError, Comparison, Region, View

FAMILY_ALPHA = 0.05
JITTER_LEVEL_STEP = 0.005     # the jitter's level over the record is applied on a grid of this step in ln


# -- settings ----------------------------------------------------------------------------------
def default_settings(n: int) -> dict:
    """Estimator sizes for n samples: Welch segment L, ACF segment M and max lag, variance window."""
    L = int(min(4096, 2 ** np.floor(np.log2(max(n // 8, 16)))))
    M = int(min(4096, 2 ** np.floor(np.log2(max(n // 4, 16)))))
    return {"nperseg": L, "acf_segment": M, "max_lag": max(4, M // 8), "window": int(max(16, n // 50)),
            "bins_per_decade": 10}


def transient_samples(model) -> int:
    """Samples until the covariance of a model started at rest is within 1 % of stationary:
    ln(0.01) / (2 ln rho), rho the spectral radius of the augmented stationary dynamics."""
    pr = predictor_of(model)
    pr.steady_state()
    F = pr._ls.F
    if F.size == 0:
        return 0
    lam = np.linalg.eigvals(F)
    if pr._Dj:
        # a plant that integrates: its walk has stationary increments from the first sample (the
        # comparison is on them); the transient is the other modes'
        lam = lam[np.abs(lam - (1.0 - LEAK)) > LEAK]
    rho = float(np.max(np.abs(lam), initial=0.0))
    if rho <= 0 or rho >= 1:
        return 0
    return int(np.ceil(np.log(0.01) / (2.0 * np.log(rho))))


# -- exact expectations from the variogram ---------------------------------------------------------------
# Predictions depend on the model and the estimator sizes only, never on the data: they are cached
# per model (its source and text) so that a live analyzer, which recomputes its views at 2 Hz on a
# window that fills up and then keeps its size, pays for them once per model revision. The cache is
# least-recently-used and bounded in bytes (entries larger than the bound are not kept).
# It is not a service.memo.Memo, whose semantics differ in what matters here: a Memo evicts in the
# order of puts (a get does not reorder), where a live analyzer's cache must keep the views it reads
# at every update however early they were put (least-recently-used); a Memo counts the bytes of
# array values only, where these values are dicts, lists and tuples of arrays (counted through);
# and an entry keyed by a model's id keeps that model alive, so that a new model cannot reuse the
# id and take its predictions.
CACHE_MAX_BYTES = 64 * 2**20
CACHE_MAX_ENTRIES = 2048                   # a filling window adds ~2 small entries per update
_CACHE: OrderedDict = OrderedDict()        # key -> (value, bytes, model kept alive for id keys)
_cache_bytes = 0
# guards _CACHE (its entries and their order) and _cache_bytes: every read and change of them holds it
# (the views of one comparison are computed in threads, and a diagnosis runs its comparisons in a
# thread beside its fits where it cannot fork)
_LOCK = threading.RLock()
VIEW_THREADS = 2                          # threads for the views of one comparison, on records ...
VIEW_THREADS_MIN = 50_000                 # ... of at least this many samples x outputs


def _model_key(model):
    """Models parsed from the same text are the same model; one without text is itself."""
    return ("text", model.source, model.text) if model.text else ("object", id(model))


def _nbytes(value) -> int:
    if isinstance(value, np.ndarray):
        return value.nbytes
    if isinstance(value, dict):
        return sum(_nbytes(v) for v in value.values())
    if isinstance(value, (list, tuple)):
        return sum(_nbytes(v) for v in value)
    return 0


def _freeze(value) -> None:
    """Cached arrays are shared by every comparison that uses them: make them read-only."""
    if isinstance(value, np.ndarray):
        value.flags.writeable = False
    elif isinstance(value, dict):
        for v in value.values():
            _freeze(v)
    elif isinstance(value, (list, tuple)):
        for v in value:
            _freeze(v)


def _cache_drop(k) -> None:
    """Entry k out (the caller holds _LOCK, and k is there)."""
    global _cache_bytes
    _, nb, _ = _CACHE.pop(k)
    _cache_bytes -= nb


def _cache_discard(k) -> None:
    """Entry k out if it is there (another thread may have dropped it since it was read)."""
    with _LOCK:
        if k in _CACHE:
            _cache_drop(k)


def _cache_put(k, value, model) -> None:
    with _LOCK:
        _cache_put_locked(k, value, model)


def _cache_put_locked(k, value, model) -> None:
    global _cache_bytes
    if k in _CACHE:
        _cache_drop(k)
    nb = _nbytes(value)
    if nb > CACHE_MAX_BYTES:
        return
    _freeze(value)
    while _CACHE and (_cache_bytes + nb > CACHE_MAX_BYTES or len(_CACHE) >= CACHE_MAX_ENTRIES):
        _cache_drop(next(iter(_CACHE)))
    _CACHE[k] = (value, nb, model if k[0][0] == "object" else None)
    _cache_bytes += nb


def _cache_get(k):
    with _LOCK:
        hit = _CACHE.get(k)
        if hit is None:
            return None
        _CACHE.move_to_end(k)
        return hit[0]


def cache_clear() -> None:
    """Forget every cached prediction (and the Welch kernels): what a fresh process starts with."""
    global _cache_bytes
    with _LOCK:
        _CACHE.clear()
        _cache_bytes = 0
    _welch_kernel.cache_clear()
    _hann_power_on_grid.cache_clear()


def _cached(model, what: str, key, compute):
    """``compute()`` once per (model, what, key), from the bounded cache."""
    k = (_model_key(model), what, key)
    hit = _cache_get(k)
    if hit is None:
        hit = compute()
        _cache_put(k, hit, model)
    return hit


def predictor_of(model):
    """The model's :class:`~service.model.predict.Predictor`, one per model (its steady state and
    linear system are computed once, not at every comparison)."""
    return _cached(model, "predictor", None, model.predictor)


def _generous(L: int) -> int:
    """L rounded up to 1/8 of its power of two (at most +12.5 %): a window that fills up asks for a
    new variogram length at every update; this way it is computed ~8 times per doubling."""
    q = 1 << max(int(L).bit_length() - 3, 4)
    return -(-int(L) // q) * q


def _gamma_parts(model, L: int) -> dict:
    """{effect id: (L, p) variogram} of the stationary-increment parts; error if not stable.
    One variogram per model is kept, computed for a generous length and sliced (the values at lag
    d do not depend on the length computed: :meth:`Predictor.variogram` builds them by doubling)."""
    k = (_model_key(model), "gamma", None)
    got = _cache_get(k)
    if got is None or got[0] < L:
        if got is not None:
            _cache_discard(k)                   # free the shorter one before computing the longer
        Lg = _generous(L)
        got = (Lg, _gamma_parts_uncached(model, Lg))
        _cache_put(k, got, model)
    return {eid: g[:L] for eid, g in got[1].items()}


def _gamma_parts_uncached(model, L: int) -> dict:
    vg = predictor_of(model).variogram(L, quantization=False)    # compare() puts in the record's own
    bad = [eid for eid, v in vg.items() if v is None]
    if bad:
        raise AnalysisError(f"model {model.name}: the plant has an unstable mode or a chain of integrators "
                            f"(a single integrator is supported), so {', '.join(bad)} has no stationary "
                            "increments to compare with")
    return vg


def _record_hash(a: np.ndarray) -> str:
    import hashlib
    return hashlib.blake2b(np.ascontiguousarray(a, float).tobytes(), digest_size=16).hexdigest()


def quantization_gamma(model, gam: dict, mean_y: np.ndarray, k0: int, jkey=None, h: str | None = None):
    """The quantizer's variogram (L, p) over this record, and its part's lag 0 (p,): its error is correlated when the signal
    moves by less than a step between samples (:mod:`service.model.effects.sensor_quantization`),
    and its conditional mean (in the mean response: :func:`quantizer_moments`) and variance depend
    on where the signal sits between the steps, so it depends on the record's own mean response
    (``mean_y`` from sample ``k0``), cached by it."""
    L = next(iter(gam.values())).shape[0]
    h = _record_hash(mean_y) if h is None else h          # the caller's, when it has hashed mean_y

    def compute():
        pr = predictor_of(model)
        mo = quantizer_moments(model, mean_y, k0, h)
        R = pr.quantization_acf(gam, pr.motion(mean_y.shape[0], mean_y, k0), moments=mo)
        return R[0] - R, R[0].copy()
    return _cached(model, "quantization", (L, k0, h, jkey), compute)


def quantizer_moments(model, mean_y: np.ndarray, k0: int = 0, h: str | None = None):
    """The quantizer's conditional moments over this record (:meth:`Predictor.quantizer_moments`:
    E[Q(x_k)] - mu_k, the part of the mean measurement the quantizer adds when the noise before it
    is under about 0.84 step), cached by the record's mean response; None when there are none."""
    h = _record_hash(mean_y) if h is None else h
    return _cached(model, "quantizer_moments", (k0, h, mean_y.shape),
                   lambda: predictor_of(model).quantizer_moments(mean_y, k0))


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


def _z2_var_linear(nu):
    """Var(z^2) of z = (X - 1) / sqrt(2 / nu), X ~ chi2_nu / nu: E z^4 = 3 + 12 / nu."""
    return 2.0 + 12.0 / np.asarray(nu, float)


def _z2_var_log(nu):
    """Var(z^2) of the standardized ln(chi2_nu / nu): its kurtosis is 3 + psi3(nu/2) / psi1(nu/2)^2
    (psi3, psi1: the polygamma functions of order 3 and 1)."""
    h = np.asarray(nu, float) / 2
    return 2.0 + polygamma(3, h) / polygamma(1, h) ** 2


# -- the jitter's modulation -------------------------------------------------------------------------------
def jitter_modulation(model, pr, mean, burn: int):
    """(m, scale), or (None, None) without a jitter. m_k (n, p): the jitter's local variance over
    its mean over the analysed samples, (ydot_k^2 + Var(ydot)) / mean. scale (p,): that mean over
    the one the predictor used (its own command over its horizon, e.g. one sweep of a chirp from
    rest), for the jitter's variogram. The predictions take the jitter as white noise of the mean
    variance (right on average); the estimators' spreads depend on how the variance is spread:
    :func:`modulation_kappa`."""
    jit = model.effects.get("sensor.jitter")
    if jit is None or not np.any(np.asarray(jit.params["std_s"], float) > 0):
        return None, None
    st = pr.steady_state()
    level = st.contributions.get("sensor.jitter")
    if st.ydot_var is None or level is None:
        return None, None
    s2 = mean.ydot[burn:] ** 2 + st.ydot_var
    mu = s2.mean(axis=0)
    var = np.broadcast_to(np.asarray(jit.params["std_s"], float) ** 2, mu.shape) * mu
    level = np.broadcast_to(level, mu.shape)
    scale = np.where(level > 0, var / np.where(level > 0, level, 1.0), 1.0)
    return np.where(mu > 0, s2 / np.where(mu > 0, mu, 1.0), 1.0), scale


def _moving_mean(m: np.ndarray, ell: int) -> np.ndarray:
    ell = int(min(max(ell, 1), m.size))
    c = np.concatenate([[0.0], np.cumsum(m)])
    return (c[ell:] - c[:-ell]) / ell


def modulation_kappa(m: np.ndarray, ell, phi) -> np.ndarray:
    """Var(estimate) / Var under stationarity for quadratic estimators that resolve ``ell`` samples
    (per point: a Welch band of K bins of L-sample Hann segments resolves 0.51 L / K, an Allan
    deviation at tau = m Ts resolves 2m, a window its own length) of a noise whose white part, a
    fraction ``phi`` of the point's expected value, has local variance m_k times its mean: with
    P = 1 - phi + phi mbar (mbar the local means over ``ell``), mean(P^2) / mean(P)^2. A Gaussian
    quadratic form's variance follows the square of its local expectation, so a jitter whose power
    follows the slope (concentrated where a chirp crosses a resonance) leaves fewer effective
    degrees of freedom than the same power spread evenly."""
    ell = np.broadcast_to(np.asarray(ell, np.int64), np.shape(phi))
    phi = np.clip(np.asarray(phi, float), 0.0, 1.0)
    out = np.ones(phi.shape)
    moments = {}
    for i, (e, f) in enumerate(zip(ell.ravel(), phi.ravel())):
        if f <= 0:
            continue
        if e not in moments:
            mb = _moving_mean(m, e)
            moments[e] = (float(mb.mean()), float(np.mean(mb**2)))
        mu1, mu2 = moments[e]
        num = (1 - f) ** 2 + 2 * f * (1 - f) * mu1 + f**2 * mu2
        out.flat[i] = max(num / ((1 - f) + f * mu1) ** 2, 1.0)
    return out


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
    if mod is not None and "sensor.jitter" in contrib:
        # the jitter's power follows the slope: each window's expectation (and spread) with it
        contrib["sensor.jitter"] = contrib["sensor.jitter"] * mod[: n_win * W].reshape(n_win, W).mean(axis=1)
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


def level_view(r, t, gam_parts, j, W, start: int, var_stat: float, walk0: float, walk_q: float, model=None,
               jkey=None):
    """The residual's mean over the variance view's windows against its prediction, 0: the mean
    response's error (a steady-state level that a saturation, a dead zone or a scale factor
    changes under a step) that every other view removes with the windows' and segments' means.
    Only for a record from rest, whose absolute level the model predicts.

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
        stat = {e: g[:, j] for e, g in gam_parts.items() if e != "sensor.bias_walk"}
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
    if mod is not None and "sensor.jitter" in parts:
        # Bartlett's J^2 terms (J: the jitter's variance; 2 J^2 at lag 0, J^2 beyond) take the
        # local variances' mean square, J^2 mean(m_k^2), when the jitter's power follows the slope
        J = float(parts["sensor.jitter"][0])
        extra = (float(np.mean(mod**2)) / float(np.mean(mod)) ** 2 - 1.0) * J**2 / (M * K)
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


@lru_cache(maxsize=4)
def _hann_power_on_grid(L: int, G: int, window: str) -> np.ndarray:
    """|H(f)|^2 of the L-sample window at f = k / (2 G), k = 0..PSD_LEAK_BINS * 2G / L."""
    w = get_window(window, L)
    s = 2 * G // L
    out = np.abs(np.fft.rfft(w, 2 * G)[: PSD_LEAK_BINS * s + 1]) ** 2
    out.setflags(write=False)                          # shared by every caller (threads included)
    return out


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

    The flat dof nu_flat (:func:`service.stats.psd._average_groups`) holds for a spectrum flat
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


def psd_view(r, Ts, gam_parts, j, L, bpd, model=None, mod=None, jkey=None, gam_fine=None, line_ids=(), qmod=None):
    """The PSD view. ``gam_fine``: {id: variogram} to a length beyond the segment (the record's), for
    the bands' dof under the model's spectrum (:func:`psd_band_dof_factor`); ``line_ids``: the tones."""
    if r.size < L:
        raise AnalysisError(f"record too short for Welch segments of {L} samples")
    est = welch(r, 1.0 / Ts, nperseg=L)
    groups = log_bin_groups(est.f, bpd)
    from ..stats.psd import _average_groups
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
    if mod is not None and "sensor.jitter" in parts:
        kappa = modulation_kappa(mod, [max(int(round(0.514 * L / len(gr))), 1) for gr in groups],
                                 parts["sensor.jitter"] / np.maximum(pred, 1e-300))
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


def allan_view(r, Ts, gam_parts_full, j, corr, model=None, mod=None, jkey=None, qmod=None):
    res = oadev(r, 1.0 / Ts, taus="octave")
    m = res.m.astype(np.int64)
    parts = {eid: allan_from_variogram(g[:, j:j + 1], m)[:, 0] for eid, g in gam_parts_full.items()}
    avar = sum(parts.values())
    total_gam = sum(g[:, j] for g in gam_parts_full.values())
    nu = allan_edf_model(total_gam, m, r.size, corr) if model is None else \
        _cached(model, "allan_edf", (j, tuple(m), r.size, corr, jkey), lambda: allan_edf_model(total_gam, m, r.size, corr))
    if mod is not None and "sensor.jitter" in parts:
        nu = nu / modulation_kappa(mod, 2 * m, parts["sensor.jitter"] / np.maximum(avar, 1e-300))
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


def model_error(views: list) -> float:
    """The model error: the views' errors (each mean(z^2), about 1 under the model) averaged with
    weights 1 / Var(error) under the model, so it is about 1 for a right model with the smallest
    spread the views allow (an ACF over a few correlation times or Allan deviations at long taus
    have few independent points and weigh less than a PSD over many independent bands)."""
    e = np.array([v.error for v in views], float)
    w = 1.0 / np.maximum(np.array([v.error_var for v in views], float), 1e-12)
    ok = np.isfinite(e) & np.isfinite(w)
    return float(np.sum(w[ok] * e[ok]) / np.sum(w[ok])) if ok.any() else float("nan")


# -- regions -------------------------------------------------------------------------------------------
def regions_of(view: View) -> list[Region]:
    """Runs of consecutive flagged points on one side of the model: a run whose z changes sign (an
    ACF above the model at short lags, below it at longer ones) is two regions, each with its own
    direction."""
    out = []
    f = view.flagged
    up = np.asarray(view.z) > 0
    i = 0
    while i < f.size:
        if not f[i]:
            i += 1
            continue
        k = i
        while k + 1 < f.size and f[k + 1] and up[k + 1] == up[i]:
            k += 1
        zz = view.z[i:k + 1]
        x0 = view.x[i] if view.x_lo is None else view.x_lo[i]
        x1 = view.x[k] if view.x_hi is None else view.x_hi[k]
        out.append(Region(view.name, view.output, float(x0), float(x1), k - i + 1,
                          float(np.max(np.abs(zz))), "above" if up[i] else "below"))
        i = k + 1
    return out


# -- entry point -----------------------------------------------------------------------------------------
def auto_burn(at_rest: bool, u) -> int | None:
    """compare()'s ``burn`` for a record: None (skip the model's transient from rest) when the
    record starts at rest (the transient is in its covariance), or when it has a command but does
    not start at rest (cut mid-stream, or the longest run after a gap: the predicted mean response
    of its command starts from zero there, the record does not); else 0."""
    return None if at_rest or (u is not None and bool(np.any(u))) else 0


def check_samples(model, t, y, u=None):
    """y (N, p) and t (N,) as float arrays, or AnalysisError naming what is wrong with them (or
    with the recorded command ``u``, (N, m), when there is one)."""
    y = np.asarray(y, float).reshape(len(y), -1)
    t = np.asarray(t, float)
    if y.shape[1] != model.p:
        raise AnalysisError(f"the recording has {y.shape[1]} measurement components, the model {model.p}")
    if u is not None:
        m = np.asarray(u, float).reshape(len(u), -1).shape[1]
        if m != model.m:
            raise AnalysisError(f"the recording's command has {m} components, the model {model.m} inputs")
    if not np.all(np.isfinite(y)):
        k = int(np.flatnonzero(~np.all(np.isfinite(y), axis=1))[0])
        raise AnalysisError(f"the measurement holds NaN or inf (first at sample {k}, t = {t[k]:g} s)")
    _gamma_parts(model, 2)          # a plant the comparison cannot follow fails here, before its overflows
    return y, t


def compare(model, t: np.ndarray, y: np.ndarray, u: np.ndarray | None = None, *, truth=None,
            burn: int | None = 0, settings: dict | None = None, revision: int = 0,
            notes: list | None = None, level: bool = False, free_start: bool = False) -> Comparison:
    """Compare samples y (N, p) at times t (N,) (regular, period model.Ts) with ``model``.

    ``u`` (N, m): the recorded command (None: the model's own command generator). ``burn``:
    samples to skip at the start (None: the model's transient from rest, capped at half the
    record). ``settings`` override :func:`default_settings`. ``level``: the record starts at rest
    (sample 0 of a noiselab stream), so its absolute level is predicted where the model predicts
    one (:attr:`Model.predicts_level`: not a sensor-only model's): add the level view.
    ``free_start``: the record does not start at rest (cut mid-stream, or the longest run after a
    gap); under a command, the mean state after the burn is fitted
    (:func:`service.model.mean_response.free_response_fit`).
    """
    y, t = check_samples(model, t, y, u)
    pr = predictor_of(model)
    try:
        mean = pr.mean_response(command=u) if u is not None else pr.mean_response(len(y))
    except ModelError as exc:
        raise AnalysisError(str(exc))
    n = len(y)
    if burn is None:
        burn = min(_cached(model, "transient", 0, lambda: transient_samples(model)), n // 2)
    fitted_start = bool(free_start and u is not None and np.any(u) and model.n_x)
    if fitted_start:
        my, myd = free_response_fit(model, y, mean.y, mean.ydot, burn, model.out_gain)
        mean = replace(mean, y=my, ydot=myd)
    y_mean = mean.y
    qmo = quantizer_moments(model, mean.y) if "sensor.quantization" in model.effects else None
    if qmo is not None:
        y_mean = mean.y + qmo.g                         # E[Q(x)]: a coarse step biases the mean
    r_all = y - y_mean
    r = r_all[burn:]
    ta = t[burn:]
    s = default_settings(r.shape[0])
    if settings:
        s.update(settings)
    L_need = max(s["nperseg"], s["acf_segment"], s["window"])
    gam = _gamma_parts(model, max(L_need, r.shape[0] + 1))
    mod, jscale = jitter_modulation(model, pr, mean, burn)
    jkey = None
    if jscale is not None:
        # the jitter's level over this record's command (the predictor's is over its own horizon),
        # on a 0.5 % grid: a live window sliding along a chirp then reuses the cached predictions
        steps = np.round(np.log(np.maximum(jscale, 1e-12)) / JITTER_LEVEL_STEP).astype(int)
        gam = dict(gam)
        gam["sensor.jitter"] = gam["sensor.jitter"] * np.exp(steps * JITTER_LEVEL_STEP)
        jkey = tuple(int(x) for x in steps)
    qmo_r = None                                       # the quantizer's moments over the analysed samples
    if "sensor.quantization" in model.effects:
        gam = dict(gam)
        h = _record_hash(mean.y[burn:])
        gq, q0 = quantization_gamma(model, gam, mean.y[burn:], burn, jkey, h)
        qmo_r = quantizer_moments(model, mean.y[burn:], burn, h)
        gam["sensor.quantization"] = gq
        if qmo is not None or (gq.shape[0] > 2 and not np.all(gq[2:] == gq[1:2])):
            # correlated: every view's prediction depends on this record's mean response, so its
            # cache key must too (a white error is the same for every record, and stays shared)
            jkey = (jkey, h, burn)
    corr = 5 * _cached(model, "transient", 0, lambda: transient_samples(model)) + 10
    # predicted variance of y_k: stationary part + the walk's growth (R_b,k = R_b,0 + k Q_b)
    st = pr.steady_state()
    walk_rate = np.broadcast_to(st.bias_var_rate * model.Ts, (model.p,))
    walk0 = sum((e.init_std**2 for e in model.effects.values() if e.id == "sensor.bias_walk"), np.zeros(model.p))
    var_stat = st.var_y if st.var_y is not None else np.full(model.p, np.nan)
    if "sensor.quantization" in model.effects and st.var_y is not None:
        # the quantizer's part over this record (its steady state has the uniform step^2 / 12)
        var_stat = var_stat - st.contributions["sensor.quantization"] + q0
    # per output: one the plant's walk reaches has no stationary variance to hold its levels to
    level_at = np.isfinite(var_stat) if level and model.predicts_level else np.zeros(model.p, bool)
    gam_short = {eid: g[:L_need] for eid, g in gam.items()}
    lines = pr.tone_ids()
    jobs = []
    for j in range(model.p):
        rj = r[:, j]
        mj = None if mod is None else mod[:, j]
        qj = qk = None
        if qmo_r is not None and qmo_r.active[j] and np.mean(qmo_r.var_y[:, j]) > 0:
            vm = np.mean(qmo_r.var_y[:, j])
            qj = np.maximum(qmo_r.var_y[:, j], 1e-9 * vm) / vm       # a window all on a level: not 0 / 0
            qk = qmo_r.k4[:, j]
        g_long = sum(g[:, j] for g in gam.values())       # to the record's length: both views' spreads
        jobs += [lambda rj=rj, j=j, gl=g_long, mj=mj, qj=qj, qk=qk: variance_view(rj, ta, gam_short, j, s["window"], model,
                                                                   gam_long=gl, mod=mj, jkey=jkey, qmod=qj, qk4=qk),
                 lambda rj=rj, j=j, gl=g_long, mj=mj, qj=qj: acf_view(rj, model.Ts, gam_short, j, s["acf_segment"],
                                                                s["max_lag"], model, gam_long=gl, jkey=jkey, mod=mj,
                                                                qmod=qj),
                 lambda rj=rj, j=j, mj=mj, qj=qj: psd_view(rj, model.Ts, gam_short, j, s["nperseg"], s["bins_per_decade"],
                                                    model, mod=mj, jkey=jkey, gam_fine=gam, line_ids=lines, qmod=qj),
                 lambda rj=rj, j=j, mj=mj, qj=qj: allan_view(rj, model.Ts, gam, j, corr, model, mod=mj, jkey=jkey,
                                                             qmod=qj)]
        if level_at[j]:
            jobs.append(lambda rj=rj, j=j: level_view(rj, ta, gam, j, s["window"], burn, float(var_stat[j]),
                                                      float(walk0[j]), float(walk_rate[j]), model, jkey=jkey))
    if r.size >= VIEW_THREADS_MIN and VIEW_THREADS > 1:
        # independent views: their transforms and array arithmetic release the GIL
        views = parallel.Pool().map(lambda f: f(), jobs, workers=VIEW_THREADS, processes=False)
    else:
        views = [f() for f in jobs]
    per_view = {}
    for name in VIEW_NAMES:
        errs = [v.error for v in views if v.name == name]
        if errs:
            per_view[name] = float(np.mean(errs))
    error = model_error(views)
    regions = [rg for v in views for rg in regions_of(v)]
    for rg in regions:
        rg.output_name = model.output_names[rg.output]
    k = np.arange(n)[:, None]
    y_sd = np.sqrt(var_stat + walk0 + k * walk_rate)
    if qmo is not None:
        # a quantizer's variance follows the mean's place between its levels (the walk included)
        y_sd[:, qmo.active] = np.sqrt(qmo.var_y[:, qmo.active])
    nts = list(notes or [])
    if fitted_start:
        nts.append(f"the record does not start at rest: analysis starts at t = {t[burn]:.3g} s ({burn} samples), "
                   f"the command's mean response from the mean state fitted there ({model.n_x} states, least squares)")
    elif burn:
        nts.append(f"analysis starts at t = {t[burn]:.3g} s, after the model's transient from rest ({burn} samples)")
    return Comparison(model_name=model.name, model_source=model.source, revision=revision, Ts=model.Ts,
                      t=t, y=y, y_mean=y_mean, y_sd=y_sd, truth=truth, views=views, error=error,
                      error_per_view=per_view, regions=regions, notes=nts,
                      output_names=tuple(model.output_names), output_units=tuple(model.output_units),
                      model_effects={eid: e.param_dict() for eid, e in model.effects.items()})
