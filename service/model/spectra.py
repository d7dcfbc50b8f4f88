"""Second-order predictions of the centered measurement: PSD, ACF, variogram and Allan variance.

Spectral conventions: PSDs are ONE-SIDED, units^2/Hz, over 0 <= f <= 1/(2 Ts), of the sampled
(discrete-time) process, so aliasing is included: S(f) = 2 Ts |T(e^{i 2 pi f Ts})|^2 for unit
white input. The ACF is the autocovariance R(d) = E[y~_{k+d} y~_k] (units^2) at lag d samples.
The Allan variance treats y as rate data with tau = m Ts: AVAR(m) = E[(ybar_{k+1} - ybar_k)^2]/2
over adjacent m-sample means, computed exactly for the sampled process from the variogram
gamma(d) = E[(y_{k+d} - y_k)^2]/2:  AVAR(m) = -(1/m^2) sum_{d=1}^{2m-1} c_m(d) gamma(d), with
c_m(d) = 2m - 3d (d <= m), -(2m - d) (m < d < 2m) (the autocorrelation of the Allan filter).
For white noise this gives var/m; for a walk of increment variance q, q (2 m^2 + 1) / (6 m), the
discrete form of K^2 tau / 3 (NIST SP 1065, Table 6).

Also here: the fit of an autocovariance by damped cosines (:func:`_damped_cosines`), the state-space
form a colored part of a linearized noise takes in the augmented system.
"""

from __future__ import annotations

import numpy as np

from .expected import expected_welch
from .lyapunov import _powers_apply

SHADOW_BLOCKS = 4         # at most so many blocks for a colored source's gain fluctuation (Predictor._gain_shadows)


class Spectra:
    """The spectra of a :class:`.predict.Predictor` (a mixin): per effect, from its steady state
    (``steady_state``, ``_ls``, ``_Pj``, ``_Dj``), its primitives and the correlated error of the
    effect acting after the sum (``after_sum``, ``quantization_acf``: a quantizer)."""

    # -- spectra -------------------------------------------------------------------------------------
    def psd(self, f: np.ndarray) -> tuple[dict, list]:
        """One-sided PSD of the centered measurement per effect at frequencies ``f`` (Hz):
        {effect id: (len(f), p)} in units^2/Hz, and spectral lines [(effect id, f_hz, power)]."""
        st = self.steady_state()
        mdl = self.model
        ls = self._ls
        f = np.asarray(f, float)
        z = np.exp(2j * np.pi * f * mdl.Ts)
        out: dict = {}
        lines = []
        if ls.Gam.shape[1]:
            n_s = ls.F.shape[0]
            M = z[:, None, None] * np.eye(n_s) - ls.F               # (nf, n_s, n_s)
            X = np.linalg.solve(M, np.broadcast_to(ls.Gam, (f.size,) + ls.Gam.shape))
            T = ls.H @ X + ls.J                                       # (nf, p, n_e)
            for eid, cols in ls.owners.items():
                c = st.contributions.get(eid)
                # NaN at an output the plant's walk reaches (no stationary spectrum there)
                out[eid] = None if c is None else \
                    2.0 * mdl.Ts * np.sum(np.abs(T[:, :, cols]) ** 2, axis=2) + np.where(np.isnan(c), np.nan, 0.0)
        for eid, kind, *prm in self._primitives():
            if kind == "white":
                out[eid] = np.broadcast_to(2.0 * mdl.Ts * prm[0], (f.size, mdl.p)).copy()
            elif kind == "jitter":
                c = st.contributions.get(eid)
                out[eid] = None if c is None else np.broadcast_to(2.0 * mdl.Ts * c, (f.size, mdl.p)).copy()
            elif kind == "walk":
                # b_{k+1} = b_k + sqrt(q) eta: S(f) = 2 Ts q / |1 - e^{-i w Ts}|^2
                with np.errstate(divide="ignore"):
                    out[eid] = 2.0 * mdl.Ts * prm[0] / (4.0 * np.sin(np.pi * f * mdl.Ts) ** 2)[:, None]
                if prm[2] is not None:                  # through the sensor's filter: times |H(f)|^2
                    out[eid] = out[eid] * prm[2].power_gain(f)
            elif kind == "tone":
                out[eid] = np.zeros((f.size, mdl.p))
                for j in range(mdl.p):
                    lines.append((eid, float(prm[1][j]), float(prm[0][j] ** 2 / 2.0), j))
        return out, lines

    def acf(self, lags: int | np.ndarray, quantization: bool = True, skip: tuple = ()) -> dict:
        """Autocovariance R(d) per stationary effect, d = 0..lags-1 (samples): {id: (L, p)}.
        The bias walk is nonstationary and has no ACF (see :meth:`variogram`). The quantizer's
        error is correlated over the model's own command (:meth:`quantization_acf`); with
        ``quantization=False`` it is left white (a caller that has the record's motion).
        ``skip``: state sources left out (not computed, no entry). Through a plant that
        integrates a source's R is the leaked model's, ~q / 2e-11 at every lag: use
        :meth:`variogram` for it."""
        L = int(lags) if np.isscalar(lags) else int(np.max(lags)) + 1
        st = self.steady_state()
        mdl = self.model
        ls = self._ls
        d = np.arange(L)
        out: dict = {}
        for eid, cols in ls.owners.items():
            if eid in skip:
                continue
            if eid not in self._Pj:
                out[eid] = None
                continue
            Pk = self._Pj[eid]
            X = np.concatenate([Pk @ ls.H.T, ls.Gam[:, cols] @ ls.J[:, cols].T], axis=1)   # (n_s, 2p)
            F, H = ls.F, ls.H
            # only the states this source reaches (when nothing else is driven by them), and only
            # up to where its slowest mode has decayed below 1e-13 (zero beyond, as in the diagnosis)
            on = np.flatnonzero(np.any(X != 0, axis=1) | np.any(Pk != 0, axis=1))
            on = np.union1d(np.arange(mdl.n_x), on)
            off = np.setdiff1d(np.arange(F.shape[0]), on)
            if off.size == 0 or not np.any(F[np.ix_(off, on)]):
                F, H, X = F[np.ix_(on, on)], H[:, on], X[on]
            rho = float(np.max(np.abs(np.linalg.eigvals(F)), initial=0.0)) if F.size else 0.0
            K = L if rho >= 1 else min(L, int(np.ceil(np.log(1e-13) / np.log(max(rho, 1e-300)))) + 2 + F.shape[0])
            FX = _powers_apply(F, X, K)                                                     # (K, n, 2p)
            p = mdl.p
            Rd = np.zeros((L, p))
            Rd[:K] = np.diagonal(np.einsum("ij,ljk->lik", H, FX[:, :, :p]), axis1=1, axis2=2)
            cross = np.diagonal(np.einsum("ij,ljk->lik", H, FX[:, :, p:]), axis1=1, axis2=2)
            Rd[1:K + 1] += cross[:L - 1]                  # H F^{d-1} Gamma J^T for d >= 1
            Rd[0] += np.sum(ls.J[:, cols] ** 2, axis=1)  # J J^T at d = 0
            out[eid] = Rd
        for eid, kind, *prm in self._primitives():
            if kind in ("white", "jitter"):
                v = prm[0] if kind == "white" else st.contributions.get(eid)
                if v is None:
                    out[eid] = None
                    continue
                R = np.zeros((L, mdl.p))
                R[0] = v
                out[eid] = R
            elif kind == "tone":            # an effect of several lines: their autocovariances add
                out[eid] = out.get(eid, 0.0) + prm[0] ** 2 / 2.0 * np.cos(2 * np.pi * d[:, None] * prm[1] * mdl.Ts)
        q = self.after_sum()
        if quantization and q is not None and all(v is not None for v in out.values()):
            gam = {eid: R[0] - R for eid, R in out.items()}
            gam.update(self._walk_variograms(L))
            out[q.id] = self.quantization_acf(gam, self.motion(max(L, self.horizon)))
        return out

    def _walk_variograms(self, L: int) -> dict:
        """{effect id: d Q_b / 2, d = 0..L-1 (L, p)} of the bias walks; through the sensor's filter
        q/2 sum_(|j|<d) (d - |j|) R_h(j) (:meth:`.effects.sensor_filter.SensorFilter.walk_variogram`)."""
        d = np.arange(L)[:, None]
        return {eid: d * prm[0] / 2.0 * np.ones(self.model.p) if prm[2] is None
                else prm[2].walk_variogram(np.broadcast_to(prm[0], (self.model.p,)), L)
                for eid, kind, *prm in self._primitives() if kind == "walk"}


    def expected_welch(self, nperseg: int, window: str = "hann") -> dict:
        """E[Welch estimate] of the centered measurement per stationary effect: {id: (nperseg//2+1, p)}
        at f_j = j / (nperseg Ts), units^2/Hz: :func:`.expected.expected_welch` of :meth:`acf`.
        The bias walk (nonstationary) has no entry."""
        L = int(nperseg)
        return expected_welch(self.acf(L), L, self.model.Ts, window)

    def variogram(self, L: int, quantization: bool = True) -> dict:
        """gamma(d) = E[(y_{k+d} - y_k)^2] / 2, d = 0..L-1, per effect {id: (L, p)}; stationary
        effects R(0) - R(d), the bias walk d Q_b / 2. ``quantization``: as in :meth:`acf`."""
        self.steady_state()
        if not self._Dj:
            out = {eid: None if R is None else R[0] - R for eid, R in self.acf(L, quantization).items()}
            out.update(self._walk_variograms(L))
            return out
        # a plant that integrates: the sources through it from (I - F) P (no R(0) at the walk's scale)
        q = self.after_sum()
        out = {eid: None if R is None else R[0] - R for eid, R in self.acf(L, False, skip=tuple(self._Dj)).items()
               if q is None or eid != q.id}
        out.update({eid: self._increments(eid, L) for eid in self._Dj})
        out.update(self._walk_variograms(L))
        if quantization and q is not None:
            R = self.quantization_acf(out, self.motion(max(L, self.horizon)))
            out[q.id] = R[0] - R
        return out

    def _increments(self, eid: str, L: int) -> np.ndarray:
        """gamma(d), d = 0..L-1 (L, p), of a source through a plant that integrates:
        R(0) - R(d) = H (I - F^d) P H^T + J J^T - H F^(d-1) Gamma J^T, with
        (I - F^d) P = sum_{j<d} F^j D, D = (I - F) P formed without cancellation."""
        ls = self._ls
        cols = ls.owners[eid]
        H, J, G = ls.H, ls.J[:, cols], ls.Gam[:, cols]
        p = self.model.p
        X = np.concatenate([self._Dj[eid] @ H.T, G @ J.T], axis=1)        # (n_s, 2p)
        FX = _powers_apply(ls.F, X, max(L - 1, 1))                          # F^j X, j = 0..L-2
        HX = np.einsum("ij,ljk->lik", H, FX)
        g = np.zeros((L, p))
        if L > 1:
            g[1:] = np.cumsum(np.diagonal(HX[:, :, :p], axis1=1, axis2=2), axis=0)[:L - 1]
            g[1:] += np.sum(J**2, axis=1) - np.diagonal(HX[:, :, p:], axis1=1, axis2=2)[:L - 1]
        return g

    def allan(self, m: np.ndarray) -> dict:
        """Allan variance per effect at averaging factors ``m`` (tau = m Ts): {id: (len(m), p)},
        exact for the sampled process (formula in the module docstring)."""
        m = np.asarray(m, dtype=np.int64)
        L = int(2 * m.max())
        out = {}
        for eid, gam in self.variogram(L).items():
            out[eid] = None if gam is None else allan_from_variogram(gam, m)
        return out


def allan_from_variogram(gam: np.ndarray, m: np.ndarray) -> np.ndarray:
    """AVAR(m) = -(1/m^2) sum_{d=1}^{2m-1} c_m(d) gamma(d), O(1) per m with prefix sums."""
    d = np.arange(gam.shape[0], dtype=float)[:, None]
    S0 = np.cumsum(gam, axis=0)               # S0[n] = sum_{d<=n} gamma(d) (gamma(0) = 0)
    S1 = np.cumsum(d * gam, axis=0)
    mm = m.astype(float)[:, None]
    a = 2 * mm * S0[m] - 3 * S1[m]
    b = -2 * mm * (S0[2 * m - 1] - S0[m]) + (S1[2 * m - 1] - S1[m])
    return -(a + b) / mm**2


def _lag_products(x: np.ndarray, D: int) -> np.ndarray:
    """mean_k x_k x_(k+d) over the overlap, d = 0..D, per column of x (N, c): (D + 1, c), by FFT."""
    N = x.shape[0]
    n2 = 1 << int(N + D).bit_length()
    spec = np.fft.rfft(x, n2, axis=0)
    return np.fft.irfft(np.abs(spec) ** 2, n2, axis=0)[:D + 1] / (N - np.arange(D + 1))[:, None]


def _nnls(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """argmin ||A x - b||, x >= 0: scipy's active-set NNLS, and where it runs out of iterations
    (it does on some of these fits: near-collinear spectra, the variance row 10^4 above the
    rest) the bounded-variable least squares of lsq_linear."""
    from scipy.optimize import lsq_linear, nnls
    try:
        return nnls(A, b, maxiter=20 * A.shape[1])[0]
    except RuntimeError:
        return lsq_linear(A, b, bounds=(0.0, np.inf), method="bvls").x


def _cosine_sums(w: np.ndarray, c: np.ndarray) -> np.ndarray:
    """sum_(d=1..D) c_d cos(w d) at each frequency w (rad/sample), c = (c_1, ..., c_D). The
    angle-addition split d = q B + r (B ~ sqrt(D)) needs cos and sin at (B + Q) multiples of w per
    frequency, not D: at D in the thousands the table of cos(w d) was most of a fit's time."""
    D = c.size
    B = max(1, int(np.ceil(np.sqrt(D + 1))))
    Q = -(-(D + 1) // B)
    H = np.zeros(Q * B)
    H[1:D + 1] = c
    H = H.reshape(Q, B)
    wr = np.outer(np.arange(B), w)                      # (B, F)
    wq = np.outer(np.arange(Q) * B, w)                  # (Q, F)
    return np.einsum("qf,qf->f", np.cos(wq), H @ np.cos(wr)) - np.einsum("qf,qf->f", np.sin(wq), H @ np.sin(wr))


def _damped_cosines(h: np.ndarray, rad: float, N: int, Ts: float, j: int, m: int, white: bool = False,
                    nblocks: int = SHADOW_BLOCKS):
    """An autocovariance h(d), d = 0..D, of a noise on input channel j, as at most ``nblocks``
    damped cosines w r^|d| cos(theta d) (a rotating AR(1) of two states; theta = 0: an AR(1)),
    and with ``white`` a white part besides. Weights w >= 0 by non-negative least squares on h's
    spectrum in relative error, at 160 frequencies log-spaced from 1 / (N Ts) to Nyquist, with
    the variance sum w = h(0) held exactly (a row weighted far above the spectrum's). Poles r from
    ``rad`` (the slowest source's) to about 1/20 (a few samples), theta from 0 to Nyquist.
    (white variance, [block (F, G, C, D) of m input channels]); a block's variance is in its G."""
    f = np.geomspace(1.0 / (N * Ts), 0.5 / Ts, 160)
    w = 2 * np.pi * f * Ts
    r = rad ** np.geomspace(1.0, np.log(0.05) / np.log(rad), 7)
    th = np.concatenate([[0.0], 2 * np.pi * Ts * np.geomspace(f[0], 0.45 / Ts, 12)])
    R, T = np.meshgrid(r, th, indexing="ij")
    R, T = R.ravel(), T.ravel()
    # the damped cosines' spectra (unit variance), as columns: (P(w - theta) + P(w + theta)) / 2
    B = 0.5 * ((1 - R**2) / (1 - 2 * R * np.cos(w[:, None] - T) + R**2)
               + (1 - R**2) / (1 - 2 * R * np.cos(w[:, None] + T) + R**2))
    if white:
        B = np.hstack([B, np.ones((f.size, 1))])
    S = h[0] + 2.0 * _cosine_sums(w, h[1:])
    scale = 1.0 / (np.abs(S) + 1e-3 * np.max(np.abs(S)))
    # the variance held: sum w / h(0) = 1 as one row weighted far above the spectrum's (whose
    # relative errors are O(1) per unit of w / h(0))
    big = 1e3 * np.sqrt(f.size)
    Mx = np.vstack([B * scale[:, None], np.full((1, B.shape[1]), big / h[0])])
    rhs = np.append(S * scale, big)
    wt = _nnls(Mx, rhs)
    order = [k for k in np.argsort(wt[:R.size])[::-1][:nblocks] if wt[k] > 0]
    keep = order + ([R.size] if white else [])
    wt_k = _nnls(Mx[:, keep], rhs)
    comps = []
    for k, wk in zip(order, wt_k):
        if wk <= 0:
            continue
        rk, tk = R[k], T[k]
        C = np.zeros((m, 1 if tk == 0 else 2))
        C[j, 0] = 1.0
        Fk = np.array([[rk]]) if tk == 0 else rk * np.array([[np.cos(tk), -np.sin(tk)], [np.sin(tk), np.cos(tk)]])
        Gk = np.sqrt(wk * (1 - rk**2)) * np.eye(Fk.shape[0])
        comps.append((Fk, Gk, C, np.zeros((m, Fk.shape[0]))))
    return (float(wt_k[-1]) if white else 0.0), comps

