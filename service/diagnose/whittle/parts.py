"""The expected periodogram of every noise source of a model, per source (its ``parts``), and
the Whittle log-likelihood of a periodogram against their sum."""

from __future__ import annotations

import numpy as np
import scipy.fft as sfft

from ...memo import Memo
from .groups import Groups
from .modes import Modes
from .periodograms import _cross_spectrum, _from_acf, _spectrum, n_freqs, taper


# -- white, autocovariance and walk sources ------------------------------------------------------------
def white_part(var: np.ndarray, M: int, groups: Groups | None = None) -> np.ndarray:
    """E I_f of white noise of variance ``var`` (p,) after differencing: 2 var (1 - cos w)(1 - ...)
    exactly for the finite record: Rd(0) = 2 var, Rd(1) = -var. ``groups``: their means instead."""
    var = np.atleast_1d(np.asarray(var, float))
    if groups is not None:
        return groups.white_unit[:, None] * var[None, :]
    # linear in var: the unit shape once per length
    unit = _WHITE.get_or_compute(M, lambda: _from_acf(np.array([[2.0], [-1.0]]), M)[:, 0])
    return unit[:, None] * var[None, :]


_WHITE = Memo(9, flush=True)            # by M


def acf_part(R: np.ndarray, M: int, groups: Groups | None = None, cross: bool = False,
             floor: bool = True) -> np.ndarray:
    """E I_f of a stationary source with autocovariance R(h) (K, p), h = 0..K-1 (zero beyond),
    independent between outputs (the quantizer's error): Rd(h) = 2 R(h) - R(h-1) - R(h+1), R(-1) =
    R(1). ``groups``: their means; ``cross``: diagonal cross-periodogram matrices. R is averaged
    over a nonstationary record (the quantizer's error follows the mean response), so its transform
    is floored at 0 where the averaging leaves it slightly negative; ``floor=False`` keeps a part
    negative by design (a quantizer that holds the measurement cancels part of the noise's own
    spectrum: Stein's term, :func:`noiselab.model.effects.sensor_quantization.quantization_acf`)."""
    R = np.asarray(R, float)
    K, p = R.shape
    Rp = np.concatenate([R, np.zeros((2, p))])
    prev = np.concatenate([R[1:2] if K > 1 else np.zeros((1, p)), Rp[:K]])     # R(h-1), h = 0..K
    Rd = 2.0 * Rp[:K + 1] - prev - Rp[1:K + 2]
    K1 = min(K + 1, M)
    a = Rd[:K1] * (taper(M)[1][:K1, None] / M)
    E = groups.spectrum(a) if groups is not None else _spectrum(a, M)
    if floor:
        E = np.maximum(E, 0.0)
    if cross:
        out = np.zeros((E.shape[0], p, p), complex)
        out[:, np.arange(p), np.arange(p)] = E
        return out
    return E


def walk_part(q: np.ndarray, M: int, groups: Groups | None = None, through=None) -> np.ndarray:
    """A random walk with increment variance q (p,) per sample: white after differencing
    (c_w(0) / M = 1). ``through``: the sensor's own filter it passes (``impulse_acf``), after which
    the differenced walk is that white noise through the filter, autocovariance q R_h(j) (not
    differenced again: the record's differences are the walk's increments filtered)."""
    q = np.atleast_1d(np.asarray(q, float))
    if through is not None:
        Rd = q * through.impulse_acf(M)
        a = Rd * (taper(M)[1][:M, None] / M)
        return np.maximum(groups.spectrum(a) if groups is not None else _spectrum(a, M), 0.0)
    return np.broadcast_to(q, (n_freqs(M) if groups is None else groups.starts.size, q.size)).copy()


# -- the expected periodogram of every noise source of a model -----------------------------------------------
def psd_sqrt(P: np.ndarray) -> np.ndarray:
    w, Q = np.linalg.eigh(0.5 * (P + P.T))
    keep = w > 1e-13 * max(float(w.max(initial=0.0)), 1e-300)
    return Q[:, keep] * np.sqrt(w[keep])


def _sub_system(ls, Pe, cols, n_x: int, De=None):
    """The states an effect's noise reaches (plant + its own), as (F, Gamma, H, P, (I - F) P)
    restricted (the last None unless given: a plant that integrates)."""
    G = ls.Gam[:, cols]
    own = np.flatnonzero(np.any(G[n_x:] != 0, axis=1) | np.any(Pe[n_x:, n_x:] != 0, axis=1)) + n_x
    S = np.concatenate([np.arange(n_x), own]).astype(np.int64)
    return ls.F[np.ix_(S, S)], G[S], ls.H[:, S], Pe[np.ix_(S, S)], None if De is None else De[np.ix_(S, S)]


def linear_part(F, G, H, J, Pe, M: int, k0: int, at_rest: bool, groups: Groups | None = None,
                cross: bool = False, De: np.ndarray | None = None) -> np.ndarray:
    """E I_f (nf, p) of one source of the augmented linear system (see the module docstring);
    ``groups``: their means (nb, p); ``cross``: the expected cross-periodogram matrices (nf or nb,
    p, p), complex Hermitian (Cov(d_{q+h}, d_q) for every pair of outputs). ``De``: (I - F) P, given
    for a plant that integrates (:func:`noiselab.model.lyapunov.lyap_leaky`): every term is then
    formed from it, without the cancellation between lags at the walk's scale."""
    p = H.shape[0]
    n = F.shape[0]
    modes = Modes(F)
    K = modes.horizon(M + 1)
    # R(h) = H F^h P H^T + [h >= 1] H F^(h-1) Gamma J^T (+ J J^T at 0): for h >= 1, H F^(h-1) Y0 with
    # Y0 = F P H^T + Gamma J^T, so the differenced Rd(h) = 2 R(h) - R(h-1) - R(h+1) is, for h >= 2,
    # -H F^(h-2) (I - F)^2 Y0: one series, and no cancellation between neighbouring lags of a slow mode
    # (R(h) = Cov(y_{k+h}, y_k), R(-h) = R(h)^T: Rd(0) = 2 R(0) - R(1) - R(1)^T)
    IF = np.eye(n) - F
    Rd = np.empty((K + 1, p, p))
    GJ = G @ J.T
    if De is None:
        Y0 = F @ Pe @ H.T + GJ                                        # (n, p)
        R0 = H @ Pe @ H.T + J @ J.T
        R1 = H @ Y0
        Rd[0] = 2 * R0 - R1 - R1.T
        if K >= 1:
            R2 = H @ F @ Y0 if K >= 2 else np.zeros((p, p))           # R(2); zero beyond a horizon of 1
            Rd[1] = 2 * R1 - R0 - R2
        IY = IF @ IF @ Y0
    else:
        # the same from D = (I - F) P: R(0) - R(1) = H D H^T + J J^T - H G J^T, so
        # Rd(0) = H (D + D^T) H^T + 2 J J^T - H G J^T - J G^T H^T,
        # Rd(1) = -H (I - F) D H^T + H (2 I - F) G J^T - J J^T, (I - F)^2 Y0 = F (I - F) D H^T + (I - F)^2 G J^T
        HGJ = H @ GJ
        Rd[0] = H @ (De + De.T) @ H.T + 2 * J @ J.T - HGJ - HGJ.T
        if K >= 1:                    # (a walk's horizon is the record: K >= 2 whenever M >= 2)
            Rd[1] = -H @ IF @ De @ H.T + H @ (2 * np.eye(n) - F) @ GJ - J @ J.T
        IY = F @ IF @ De @ H.T + IF @ IF @ GJ
    if K >= 2:
        modes.series(H, -IY, K - 1, out=Rd[2:])
    if not cross:
        idx = np.arange(p)
        Rd = Rd[:, idx, idx]
    # a(h) = c_w(h) Rd(h) / M
    K = min(Rd.shape[0], M)
    cw = taper(M)[1][:K]
    a = Rd[:K] * (cw.reshape((K,) + (1,) * (Rd.ndim - 1)) / M)
    w = None
    if at_rest:
        Gs = psd_sqrt(Pe)
        if Gs.shape[1]:
            Kr = min(modes.horizon(k0 + M + 1), k0 + M + 1)
            # w_q = v_{k0+q+1} - v_{k0+q} = H F^(k0+q) (F - I) P^(1/2), q < Kr - k0 - 1
            Lw = Kr - k0 - 1
            if Lw > 0:
                left = H if k0 == 0 else H @ np.linalg.matrix_power(F, k0)
                w = modes.series(left, -(IF @ Gs), Lw)                   # (Lw, p, c)
                w *= taper(M)[0][:Lw, None, None]
    Lw = 0 if w is None else w.shape[0]
    short = groups is not None and groups.fast(max(K, Lw))
    if w is not None and short:
        # sum_c W_ic(f) conj(W_jc(f)) = sum_h rho_ij(h) e^{-i w h}, rho_ij(h) = sum_{q,c} w_{i,q+h,c}
        # w_{j,q,c} the cross-correlation of the tapered w (rho(-h) = rho(h)^T, as a(h)): subtracted
        # from a(h) it leaves E I_f = the group transform of a, exactly
        n2 = 1 << int(2 * Lw - 1).bit_length()
        Wf = sfft.rfft(w, n=n2, axis=0)
        if cross:
            rho = sfft.irfft(np.einsum("fic,fjc->fij", Wf, np.conj(Wf)), n=n2, axis=0)[:Lw]   # (Lw, p, p)
        else:
            rho = sfft.irfft(np.sum(np.abs(Wf) ** 2, axis=2), n=n2, axis=0)[:Lw]           # (Lw, p)
        if Lw > K:
            a = np.concatenate([a, np.zeros((Lw - K,) + a.shape[1:])])
        a[:Lw] -= rho / M
    if short:
        return groups.cross(a) if cross else groups.spectrum(a)
    # long memory (a correlation time near the record's): every bin, the correction as |W_c(f)|^2
    E = _cross_spectrum(a, M) if cross else _spectrum(a, M)
    if w is not None:
        Wf = sfft.rfft(np.ascontiguousarray(w.transpose(1, 2, 0)), n=M, axis=-1)[:, :, :E.shape[0]]   # (p, c, nf)
        if cross:
            E -= np.einsum("icf,jcf->fij", Wf, np.conj(Wf)) / M
        else:
            E -= (np.sum(Wf.real ** 2 + Wf.imag ** 2, axis=1) / M).T
    return E if groups is None else groups.mean(E)


# :func:`expected_parts`' cache of one record (:func:`parts_cache`): a part is mostly a group mean per
# output, ~1000 groups even at 10^6 samples (8.7 kB for one output; 154 kB as a 3-output
# cross-spectral matrix), but the tone screen's are per frequency bin (4 MB per output at 10^6
# samples): the count alone does not bound them
PARTS_CACHE = 1024         # parts kept (the oldest go first) ...
PARTS_CACHE_BYTES = 128 << 20     # ... and at most this many bytes of them


def parts_cache() -> Memo:
    """A cache for :func:`expected_parts`, bounded by :data:`PARTS_CACHE` entries and
    :data:`PARTS_CACHE_BYTES` bytes, shared by the threads that fit one record's candidates."""
    return Memo(PARTS_CACHE, nbytes=PARTS_CACHE_BYTES)


def expected_parts(model, M: int, k0: int, at_rest: bool, ydot_sq: np.ndarray | None = None,
                   skip: tuple = (), cache: Memo | None = None,
                   groups: Groups | None = None, cross: bool = False) -> dict:
    """{effect id: E I_f (nf, p)} for every effect of ``model`` that owns noise, for the
    differenced residual of M samples starting after sample k0. ``at_rest``: the record starts at
    rest at sample 0 (the from-rest correction applies). ``ydot_sq``: mean square of the predicted
    mean slope per output over the record (for the jitter; default: the predictor's); with
    ``cross``, the matrix of mean products (p, p). Tones are deterministic in a record and handled
    by the caller: their ``tone`` primitives add no part here. ``skip``: effects left out. ``cache``: a :func:`parts_cache` reused across calls, keyed by each
    source's own sub-system (an effect whose transfer did not change is not recomputed). ``groups``: the parts
    as group means (nb, p) (:class:`Groups`, fast on long records). ``cross``: the expected
    cross-periodogram matrices (nf or nb, p, p), complex Hermitian: sources through the plant (and
    the jitter: one sampling instant for all outputs) correlate the outputs, sensor white noise and
    the bias walk do not."""
    pr = model.predictor()
    pr.steady_state()
    ls = pr._ls
    p = model.p
    parts: dict = {}
    ydot_cov = np.zeros((p, p))
    for eid, cols in ls.owners.items():
        Pe = pr._Pj.get(eid)
        if Pe is None:
            raise ValueError(f"{eid}: no stationary prediction (the plant is not stable)")
        Jd = ls.Jd[:, cols]
        ydot_cov += ls.Hd @ Pe @ ls.Hd.T + Jd @ Jd.T
        if eid in skip:
            continue
        F, G, H, Ps, Ds = _sub_system(ls, Pe, cols, ls.n_x, pr._Dj.get(eid))
        J = ls.J[:, cols]
        key = None
        if cache is not None:
            key = (eid, M, k0, at_rest, groups is not None, cross, F.tobytes(), G.tobytes(), H.tobytes(),
                   J.tobytes())
            got = cache.get(key)
            if got is not None:
                parts[eid] = got
                continue
        E = linear_part(F, G, H, J, Ps, M, k0, at_rest, groups, cross, Ds)
        if cache is not None:
            cache.put(key, E)
        parts[eid] = E
    if ydot_sq is None:
        mean = pr.mean_response()
        ydot_sq = mean.ydot.T @ mean.ydot / mean.ydot.shape[0] if cross else np.mean(mean.ydot**2, axis=0)

    def unit_times(var):
        """The differenced white unit times a variance (p,) or, with ``cross``, a covariance (p, p)."""
        if not cross:
            return white_part(var, M, groups)
        unit = white_part(np.ones(1), M, groups)[:, 0]
        V = np.diag(var) if np.ndim(var) == 1 else var
        return unit[:, None, None] * V[None].astype(complex)

    for eid, kind, *prm in pr._primitives():
        if eid in skip:
            continue
        if kind == "white":
            add = unit_times(np.broadcast_to(prm[0], (p,)).astype(float))
        elif kind == "walk":
            q = walk_part(np.broadcast_to(prm[0], (p,)), M, groups, prm[2])
            add = q if not cross else q[:, :, None] * np.eye(p)[None].astype(complex)
        elif kind == "jitter":
            cov = ydot_sq + ydot_cov if cross else ydot_sq + np.diag(ydot_cov)
            parts[eid] = unit_times(prm[0] * cov)
            continue
        else:
            continue
        parts[eid] = parts.get(eid, 0) + add
    return parts


def loglik(I: np.ndarray, E: np.ndarray, M: int) -> float:
    """Whittle log-likelihood -(1/kappa) sum [ln E + I / E] over frequencies and outputs."""
    E = np.maximum(E, 1e-300)
    return float(-np.sum(np.log(E) + I / E) / taper(M)[2])
