"""The likelihood the diagnosis ranks and fits effects with: a debiased Whittle likelihood of the
differenced residual, exact for a record that starts at rest.

Symbols -> names:

=============  ==============  =================================================================
symbol         name            meaning
=============  ==============  =================================================================
r_k            ``r``           residual y_k - E[y_k] (measurement minus the model's mean response)
d_q            ``d``           differenced residual r_{q+k0+1} - r_{q+k0}, q = 0..M-1
I_f            ``I``           periodogram |sum_q w_q d_q e^{-i 2 pi f q / M}|^2 / M, f = 0..nf-1
E_f            ``E``           its expectation under the model, per effect (``parts``)
R(h), R_d(h)   ``R``, ``Rd``   autocovariance of r and of d at lag h samples
=============  ==============  =================================================================

Why this form:

* Differencing makes the bias random walk white (its increments are iid), so the nonstationary
  effect of the catalogue enters like every other one, and removes any constant offset.
* The periodogram's expectation is computed exactly for the finite record (the "debiased Whittle
  likelihood", Sykulski, Olhede, Guillaumin, Lilly & Early 2019, Biometrika 106(2)):
  E I_f = sum_{|h|<M} (1 - |h|/M) R_d(h) e^{-i w_f h}, so leakage from resonances and steep
  spectra is inside the prediction, never read as a missing effect.
* A record that starts at rest (noiselab's emulator starts every state at zero) is not stationary:
  P_k = P - F^k P F^T^k (the solution of P_{k+1} = F P_k F^T + Gamma Gamma^T from P_0 = 0, seed
  section 4), so Cov(s_k, s_l) = [stationary] - F^k P F^T^l for every k, l. The correction is
  separable, and its effect on E I_f is -(1/M) sum_c |sum_q w_{q,c} e^{-i w_f q}|^2 with
  w_q = v_{q+1} - v_q, v_k = H F^k P^{1/2}. No samples need to be thrown away as burn-in.
* The differenced series is tapered (Tukey, 10 % cosine at each end, normalized to sum w^2 = M)
  before the transform. Without it the end-point term (r_M - r_0), common to every bin, leaks
  Var(r)/M into all low frequencies and buries a bias walk there; with it E I_f =
  (1/M) sum_h c_w(h) R_d(h) e^{-i w_f h}, c_w the taper's autocorrelation (Dahlhaus 1988).
* Whittle: l = -(1/kappa) sum_f [ln E_f + I_f / E_f] (Whittle 1953). Several outputs: the
  cross-periodogram matrices I_f = X_f X_f^H / M against their expectations E_f (p x p, complex
  Hermitian), l = -(1/kappa) sum_f [ln det E_f + tr(E_f^-1 I_f)] (Brillinger 1981 ch. 7): two
  sensors of one plant share its noise, and summing their separate likelihoods would count that
  evidence twice. The cross terms come from the same sums of exponentials (Cov(y_{k+h}, y_k) =
  R(h), R(-h) = R(h)^T); sensor white noise and the bias walk are per output, the jitter's one
  sampling instant correlates the outputs through their slopes. kappa = M sum w^4 /
  (sum w^2)^2 corrects for the correlation the taper puts between neighbouring bins (the
  likelihood's curvature would otherwise be overstated by that factor).
* What the taper takes (sample q weighs u_q^2 in the periodogram, u the Tukey shape: nothing at
  the record's ends) is given back in the time domain by :class:`Ramps` with the complementary
  weights 1 - u_q^2: a step at t = 0 from rest has its whole transient there. The ends are not
  simply left untapered: at the start of a record from rest the process noise is zero but the
  sensor noise is not, so an untapered first sample r_0 is common to every low-frequency bin,
  whose periodogram values are then far from independent (on a null record with a chirp, the
  bias walk's likelihood-ratio score had 4x its model spread).

Every autocovariance is a sum of exponentials: with F = V diag(lambda) V^-1 (the augmented
dynamics of :class:`service.model.predict.LinearSystem`), R(h) = Re sum_i c_i lambda_i^(h-1) for
h >= 1 (Percival & Walden 1993 ch. 9 for AR forms), computed in blocks up to where it has decayed
below 1e-13 of its start. Defective F (e.g. a critically damped plant) falls back to repeated
products of F.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.fft as sfft

from ..memo import Memo

TAPER = 0.2              # Tukey taper: the cosine parts cover 10 % of the record at each end
DECAY = 1e-13            # |lambda|^h below which an exponential's tail is dropped
COND_MAX = 1e8           # eigenvector condition number beyond which F is treated as defective


# -- periodogram of the differenced residual ---------------------------------------------------------------
def n_freqs(M: int) -> int:
    """Fourier frequencies used: f = 0..(M-1)//2 (DC included: for the differenced series it is the
    tapered total increment, the most direct evidence of a walk; no Nyquist). Index k is k / (M Ts)."""
    return (M - 1) // 2 + 1


_TAPERS = Memo(9, flush=True)           # by M


def taper(M: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Tukey taper w (M,) with sum w^2 = M, its autocorrelation c_w(h) = sum_q w_q w_{q+h}
    (h = 0..M-1) and kappa = M sum w^4 / (sum w^2)^2."""
    def compute():
        from scipy.signal.windows import tukey
        w = tukey(M, TAPER) if M > 2 else np.ones(M)
        w *= np.sqrt(M / np.sum(w**2))
        F = np.fft.rfft(w, 2 * M)
        cw = np.fft.irfft(np.abs(F) ** 2, 2 * M)[:M]
        kappa = float(M * np.sum(w**4) / np.sum(w**2) ** 2)
        return w, cw, kappa
    return _TAPERS.get_or_compute(M, compute)


def slope_power(yk: np.ndarray, cross: bool) -> np.ndarray:
    """The jitter's slope power as the tapered periodogram of the differenced record sees it:
    sum_q w_q^2 (y_q+1 y_q+1^T + y_q y_q^T) / (2 M) over the M differences of yk (M + 1, p), the
    matrix (``cross``) or its diagonal. For a white noise of variance s_k^2,
    E I_f = (2 - 2 cos w_f) sum_k w_k^2 s_k^2 / M (to first order in the taper's slope), so the
    jitter's std_s^2 multiplies this weighted mean, not the plain one: under a PRBS or a chirp the
    slope's power is not spread evenly over the record (the plain mean biased std_s by 2 % on a
    PRBS record)."""
    w2 = taper(yk.shape[0] - 1)[0] ** 2
    if cross:
        a, b = yk[1:] * w2[:, None], yk[:-1] * w2[:, None]
        return (a.T @ yk[1:] + b.T @ yk[:-1]) / (2 * w2.size)
    return (w2 @ (yk[1:] ** 2 + yk[:-1] ** 2)) / (2 * w2.size)


def periodogram(r: np.ndarray, k0: int = 0, cross: bool = False) -> np.ndarray:
    """I_f (nf, p) of the tapered d_q = r_{k0+q+1} - r_{k0+q}, f = 0..nf-1; ``cross``: the
    cross-periodogram matrices I_f = X_f X_f^H / M (nf, p, p), complex Hermitian."""
    d = np.diff(r[k0:], axis=0)
    M = d.shape[0]
    w = taper(M)[0]
    X = sfft.rfft(np.ascontiguousarray((d * w[:, None]).T), axis=-1).T[:n_freqs(M)]    # rows: one output each
    if cross:
        return X[:, :, None] * np.conj(X[:, None, :]) / M
    return (np.abs(X) ** 2) / M


def _from_acf(Rd: np.ndarray, M: int) -> np.ndarray:
    """E I_f from the differenced autocovariance Rd (K, p), K <= M (zero beyond):
    (1/M) sum_h c_w(|h|) Rd(h) e^{-i w h}."""
    K = min(Rd.shape[0], M)
    return _spectrum(Rd[:K] * (taper(M)[1][:K, None] / M), M)


def _spectrum(a: np.ndarray, M: int) -> np.ndarray:
    """a(0) + 2 sum_{h>=1} a(h) cos(w_f h) at the Fourier frequencies w_f = 2 pi f / M, f < nf."""
    K = a.shape[0]
    nf = n_freqs(M)
    if K <= 8:                                   # short (white): the cosine sum directly
        w = 2 * np.pi * np.arange(nf) / M
        E = np.broadcast_to(a[0], (nf, a.shape[1])).copy()
        for h in range(1, K):
            E += 2.0 * np.cos(w * h)[:, None] * a[h]
        return E
    E = 2.0 * sfft.rfft(np.ascontiguousarray(a.T), n=M, axis=-1).real.T - a[0]
    return E[:nf]


def _cross_spectrum(a: np.ndarray, M: int) -> np.ndarray:
    """S_f = a(0) + sum_{h>=1} [a(h) e^{-i w_f h} + a(h)^T e^{i w_f h}] (nf, p, p) from a(h)
    (K, p, p), a(h) the cross-covariance sequence Cov(x_{k+h}, x_k) (a(-h) = a(h)^T): C + C^H - a(0)
    with C_f = sum_{h>=0} a(h) e^{-i w_f h}."""
    K, p, _ = a.shape
    C = sfft.rfft(np.ascontiguousarray(a.reshape(K, p * p).T), n=M, axis=-1).T[:n_freqs(M)].reshape(-1, p, p)
    return C + np.conj(C.transpose(0, 2, 1)) - a[0]


# -- frequency groups: the expected periodogram's group means without the full transform ------------------
class Groups:
    """Fourier bins f = 0..nf-1 in groups at most ``rel`` f wide (single bins up to 1/rel), and the
    group means of an expected periodogram E_f = a(0) + 2 sum_{h>=1} a(h) cos(2 pi f h / M) computed
    exactly from a(h) without the length-M transform when a(h) is short:

    * above F_low = n / rel the groups are made of whole aligned blocks of n bins (n a divisor of
      M near sqrt(rel M)). The mean over block b (bins bn..bn+n-1) is
      a(0) + 2 Re sum_h a(h) D(h) e^{-i 2 pi b h / L}, L = M / n, D(h) = (1/n) sum_{j<n}
      e^{-i 2 pi j h / M}: the exponential is L-periodic in h, so a(h) D(h) folded modulo L and one
      length-L transform give every block mean;
    * the single bins below F_low (and the < n bins after the last whole block) by the chirp z
      transform (Bluestein 1970): a transform of length ~ K + F_low for a(h) of K lags.

    Every M gets the same group layout whatever the part, so the periodogram is grouped alike."""

    def __init__(self, M: int, rel: float):
        self.M, self.rel = M, rel
        nf = self.nf = n_freqs(M)
        target = math.sqrt(rel * M)
        n = max((d for d in range(1, int(target) + 1) if M % d == 0), default=1)
        if n < 4 or n / rel >= nf:
            n = 1
        self.n = n
        self.F_low = int(round(n / rel)) if n > 1 else nf
        F_low = self.F_low
        starts, i = [], 0
        while i < nf:
            starts.append(i)
            if i < F_low:
                i = min(i + max(1, int(i * rel)), F_low)
            else:
                i += n * max(1, int(i * rel) // n)
        self.starts = np.asarray(starts, np.int64)
        self.sizes = np.diff(np.append(self.starts, nf)).astype(float)
        if n > 1:
            self.L = M // n
            self.b0 = F_low // n                       # first block above F_low
            self.b1 = nf // n                          # one past the last whole block
            self.tail = nf - self.b1 * n               # bins after the last whole block
            # the units the groups are sums of: low bins (1 bin), blocks (n bins), tail bins (1 bin)
            unit_f = np.concatenate([np.arange(F_low), np.arange(self.b0, self.b1) * n,
                                     np.arange(self.b1 * n, nf)])
            self.unit_w = np.concatenate([np.ones(F_low), np.full(self.b1 - self.b0, float(n)),
                                          np.ones(self.tail)])
            self.unit_starts = np.searchsorted(unit_f, self.starts)
        self._D = np.ones(1, complex)
        self._chirps = Memo(17, flush=True)         # by (first bin, bins, length)
        self.white_unit = self.mean(_from_acf(np.array([[2.0], [-1.0]]), M))[:, 0]

    def mean(self, A: np.ndarray) -> np.ndarray:
        """Group means (nb, ...) of a full array (nf, ...)."""
        return np.add.reduceat(A, self.starts, axis=0) / self.sizes.reshape((-1,) + (1,) * (A.ndim - 1))

    def fast(self, K: int) -> bool:
        """Whether a(h) of K lags takes the fast path (chirp z and folded blocks)."""
        return self.n > 1 and K + self.F_low <= self.M // 8

    def spectrum(self, a: np.ndarray) -> np.ndarray:
        """Group means of E_f (nb, p) from a(h) (K, p), as ``mean(_spectrum(a, M))``."""
        if not self.fast(a.shape[0]):
            return self.mean(_spectrum(a, self.M))
        return 2.0 * self._sums(a).real - a[0]

    def cross(self, a: np.ndarray) -> np.ndarray:
        """Group means of the cross-spectrum S_f (nb, p, p) from a(h) (K, p, p), as
        ``mean(_cross_spectrum(a, M))``."""
        K, p, _ = a.shape
        if not self.fast(K):
            return self.mean(_cross_spectrum(a, self.M))
        C = self._sums(a.reshape(K, p * p)).reshape(-1, p, p)
        return C + np.conj(C.transpose(0, 2, 1)) - a[0]

    def _sums(self, a: np.ndarray) -> np.ndarray:
        """Group means of C_f = sum_{h>=0} a(h) e^{-i w_f h} (nb, q) complex, from a(h) (K, q)."""
        K, q = a.shape
        units = np.empty((self.unit_w.size, q), complex)
        units[:self.F_low] = self._czt(a, 0, self.F_low)
        # block means: a(h) D(h) folded modulo L, one transform
        D = self._kernel(K)
        g = np.zeros((-(-K // self.L) * self.L, q), complex)
        g[1:K] = a[1:K] * D[1:K, None]
        G = sfft.fft(g.reshape(-1, self.L, q).sum(axis=0), axis=0)
        nb = self.b1 - self.b0
        units[self.F_low:self.F_low + nb] = a[0] + G[self.b0:self.b1]
        if self.tail:
            units[self.F_low + nb:] = self._czt(a, self.b1 * self.n, self.tail)
        return np.add.reduceat(units * self.unit_w[:, None], self.unit_starts, axis=0) / self.sizes[:, None]

    def _kernel(self, K: int) -> np.ndarray:
        """D(h) = (1/n) sum_{j<n} e^{-i 2 pi j h / M}, h = 0..K-1 (cached, extended on demand).
        The one read of ``self._D`` is what is returned: another thread may replace it meanwhile,
        by a shorter one too (every length's values agree)."""
        D = self._D
        if D.size < K:
            size = 1 << int(K - 1).bit_length()
            h = np.arange(1, size)
            th = 2 * np.pi * h / self.M
            D = np.ones(size, complex)
            D[1:] = (1 - np.exp(-1j * self.n * th)) / (self.n * (1 - np.exp(-1j * th)))
            self._D = D
        return D

    def _czt(self, a: np.ndarray, f0: int, m: int) -> np.ndarray:
        """X_f = sum_h a(h) e^{-i 2 pi f h / M} for f = f0..f0+m-1 (m, p): Bluestein's chirp
        (f h = (f^2 + h^2 - (f - h)^2) / 2), the phases reduced modulo 2M in integers."""
        K = a.shape[0]
        size = 1 << int(K + m - 2).bit_length()
        M2 = 2 * self.M
        key = (f0, m, size)

        def chirp():
            # filter c(j) = e^{i pi j^2 / M} for j = f - h in [f0 - size + m, f0 + m); index j - (f0 - size + m)
            j = np.arange(f0 - size + m, f0 + m, dtype=np.int64)
            c = np.exp(1j * np.pi * ((j * j) % M2) / self.M)
            f = np.arange(f0, f0 + m, dtype=np.int64)
            return sfft.fft(c), np.exp(-1j * np.pi * ((f * f) % M2) / self.M)
        Cf, post = self._chirps.get_or_compute(key, chirp)
        h = np.arange(K, dtype=np.int64)
        x = np.zeros((size, a.shape[1]), complex)
        x[:K] = a * np.exp(-1j * np.pi * ((h * h) % M2) / self.M)[:, None]
        # y(f0 + i) = sum_h x(h) c(f0 + i - h): a circular convolution of length size >= K + m - 1,
        # free of wrap-around at the outputs i + size - m
        y = sfft.ifft(sfft.fft(x, axis=0) * Cf[:, None], axis=0)
        return y[size - m:] * post[:, None]


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
    spectrum: Stein's term, :func:`service.model.effects.sensor_quantization.quantization_acf`)."""
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


def walk_part(q: np.ndarray, M: int, groups: Groups | None = None) -> np.ndarray:
    """A random walk with increment variance q (p,) per sample: white after differencing
    (c_w(0) / M = 1)."""
    q = np.atleast_1d(np.asarray(q, float))
    return np.broadcast_to(q, (n_freqs(M) if groups is None else groups.starts.size, q.size)).copy()


# -- sums of exponentials --------------------------------------------------------------------------------------
class Modes:
    """F = V diag(lam) V^-1, with F^h X evaluated as sums of exponentials (or by products when F is
    defective). The powers lam^j are kept per kind of mode (real; complex of positive imaginary
    part) and shared by the series of one F (a source's lags and its from-rest correction)."""

    def __init__(self, F: np.ndarray):
        self.F = F
        n = F.shape[0]
        self.n = n
        self._tab: dict = {}
        if n == 0:
            self.ok = True
            self.lam = np.zeros(0)
            return
        lam, V = np.linalg.eig(F)
        self.ok = bool(np.linalg.cond(V) < COND_MAX)
        self.lam, self.V = lam.astype(complex), V
        self.Vi = np.linalg.inv(V) if self.ok else None
        mag = np.abs(lam)
        self.rho = float(np.max(mag, initial=0.0))
        # each mode's own horizon (a fast plant mode beside a slow bias): |lam|^h < DECAY beyond it
        with np.errstate(divide="ignore"):
            self.hz = np.where(mag == 0, 1.0, np.where(mag < 1, np.log(DECAY) / np.log(np.maximum(mag, 1e-300)) + 2,
                                                     np.inf))
        self._ridx = np.flatnonzero(self.lam.imag == 0)
        self._cidx = np.flatnonzero(self.lam.imag > 0)
        # LAPACK returns the eigenvalues of a real matrix in adjacent, exactly conjugate pairs (the
        # positive imaginary part first): then :meth:`_pairs` needs no search
        i = self._cidx
        self._adjacent = bool(np.count_nonzero(self.lam.imag < 0) == i.size and (i.size == 0 or (
            i[-1] + 1 < n and np.all(self.lam[i + 1] == np.conj(self.lam[i])))))

    def _pairs(self, coef: np.ndarray):
        """Conjugate pairs once: Re(c lam^h + conj(c) conj(lam)^h) = Re(2 c lam^h) (F and the
        weights are real). Returns the modes kept and their coefficients."""
        i = self._cidx
        if self._adjacent:
            # the pairing below, without its search: the partner of i is i + 1 when the weights are
            # conjugate too (np.allclose(coef[i + 1], conj(coef[i]), rtol=1e-9, atol=1e-300))
            c = np.conj(coef[i])
            if np.all(np.abs(coef[i + 1] - c) <= 1e-300 + 1e-9 * np.abs(c)):
                keep = np.ones(self.n, bool)
                keep[i + 1] = False
                coef = coef.copy()
                coef[i] *= 2.0
                return keep, coef
        return self._pairs_search(self.lam, coef)

    @staticmethod
    def _pairs_search(lam: np.ndarray, coef: np.ndarray):
        """:meth:`_pairs` for any order of the eigenvalues."""
        n = lam.size
        keep = np.ones(n, bool)
        coef = coef.copy()
        used = np.zeros(n, bool)
        for i in range(n):
            if used[i] or lam[i].imag <= 0:
                continue
            j = [k for k in range(n) if not used[k] and k != i and lam[k].imag < 0
                 and np.isclose(lam[k], np.conj(lam[i]), rtol=1e-12, atol=1e-15)
                 and np.allclose(coef[k], np.conj(coef[i]), rtol=1e-9, atol=1e-300)]
            if j:
                used[i] = used[j[0]] = True
                keep[j[0]] = False
                coef[i] = 2.0 * coef[i]
        return keep, coef

    def _powers(self, cols: np.ndarray, nb: int) -> np.ndarray:
        """lam[cols]^j, j < nb (nb, len(cols)), by products (no exponentials): real for real modes.
        ``cols`` are modes of one kind, in increasing order. Columns of the kind's table, grown
        when a longer one is asked for (a column's products do not depend on the others)."""
        real = bool(self.lam[cols[0]].imag == 0)
        kind = self._ridx if real else self._cidx
        pos = np.searchsorted(kind, cols)
        if np.any(pos >= kind.size) or not np.array_equal(kind[np.minimum(pos, kind.size - 1)], cols):
            kind, pos = cols, np.arange(cols.size)          # (a mode outside the table: its own products)
            tab = None
        else:
            tab = self._tab.get(real)
        if tab is None or tab.shape[0] < nb:
            lm = self.lam[kind].real if real else self.lam[kind]
            tab = np.empty((nb, kind.size), float if real else complex)
            tab[0] = 1.0
            if nb > 1:
                tab[1:] = lm
                np.cumprod(tab, axis=0, out=tab)
            if kind is not cols:
                self._tab[real] = tab
        return tab[:nb] if pos.size == tab.shape[1] else tab[:nb, pos]

    def horizon(self, M: int) -> int:
        """Lags until every mode has decayed below DECAY, capped at M."""
        if self.n == 0:
            return 1
        if self.rho <= 0:
            return min(M, self.n + 2)
        if self.rho >= 1:
            return M
        return int(min(M, np.ceil(np.log(DECAY) / np.log(self.rho)) + 2))

    def series(self, left: np.ndarray, right: np.ndarray, K: int, block: int = 1 << 15,
               out: np.ndarray | None = None):
        """S_h = left F^h right for h = 0..K-1: (K, a, b) real, left (a, n), right (n, b); written
        into ``out`` when given (C-contiguous, (K, a, b))."""
        a, b = left.shape[0], right.shape[1]
        if out is None:
            out = np.empty((K, a, b))
        elif out.shape != (K, a, b) or not out.flags.c_contiguous:
            raise ValueError(f"series: out must be C-contiguous of shape {(K, a, b)}")   # (a reshape would copy)
        if self.n == 0:
            out[:] = 0.0
            return out
        if self.ok:
            L = left @ self.V                      # (a, n)
            Rm = self.Vi @ right                   # (n, b)
            coef = (L[:, :, None] * Rm[None, :, :]).transpose(1, 0, 2).reshape(self.n, a * b)   # (n, a b)
            keep, coef = self._pairs(coef)
            # modes whose weight is rounding (a plant mode the source's noise does not reach) dropped
            big = np.max(np.abs(coef[keep]), axis=1) > 1e-14 * max(float(np.max(np.abs(coef[keep]), initial=0.0)), 1e-300)
            keep[np.flatnonzero(keep)[~big]] = False
            idx = np.flatnonzero(keep)
            nb = min(K, block)
            kinds = []
            for sel in (idx[self.lam[idx].imag == 0], idx[self.lam[idx].imag != 0]):
                if sel.size:
                    real = bool(self.lam[sel[0]].imag == 0)
                    lm = self.lam[sel].real if real else self.lam[sel]
                    kinds.append((sel, lm, self._powers(sel, nb), coef[sel].real if real else coef[sel]))
            done = 0                                 # rows of ``out`` written
            for h0 in range(0, K, nb):
                m = min(K, h0 + nb) - h0
                acc = out[h0:h0 + m].reshape(m, a * b)
                first = True
                for sel, lm, P, cf in kinds:
                    act = np.flatnonzero(self.hz[sel] > h0)
                    if act.size == 0:
                        continue
                    whole = act.size == sel.size
                    pw = P[:m] if whole else P[:m, act]
                    c = cf if whole else cf[act]
                    if h0:
                        pw = pw * (lm[act] ** h0 if pw.dtype == float else np.exp(h0 * np.log(lm[act])))
                    term = pw @ c if pw.dtype == float else pw.real @ c.real - pw.imag @ c.imag
                    if first:
                        acc[...] = term
                        first = False
                    else:
                        acc += term
                if first:
                    break
                done = h0 + m
            out[done:] = 0.0
            return out
        X = right.astype(float)
        for h in range(K):                          # defective F: plain products
            out[h] = left @ X
            X = self.F @ X
        return out


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
    for a plant that integrates (:func:`service.model.lyapunov.lyap_leaky`): every term is then
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
            q = walk_part(np.broadcast_to(prm[0], (p,)), M, groups)
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


# -- the taper's ramps: what the tapered periodogram leaves out ---------------------------------------------
RAMP_MIN = 256           # shortest differenced record given a ramp term
RAMP_LOG2_SEG = 13       # the whitener's Welch segments: up to 2^13 samples (M / 8 at most), half as many taps
RAMP_FLOOR = 1e-5       # the whitener's spectrum floor, relative to its mean


class Ramps:
    """l_ramp: the part of the differenced residual the taper weighs down, in the time domain.

    The tapered periodogram gives sample q the weight u_q^2 (u the Tukey shape, 0 at the ends, 1
    in the middle): a mean response that changes only in the first or last tenth of the record (a
    step at t = 0 from rest: its whole transient) leaves almost no trace in it. The samples'
    complement c_q = 1 - u_q^2 enters here instead:

        e = h * d (per output),   l_ramp = -(nu / 2) ln(sum_q c_q e_q^2 / nu),   nu = sum_q c_q

    with h a minimum-phase whitening filter of the residual's differenced spectrum (a generalized
    least-squares fit of the mean response over the ramps) and the noise scale profiled out. The
    whitener is estimated once per record, from the nominal model's residual (Welch, Hann
    segments; cepstral minimum phase, Oppenheim & Schafer 2010 ch. 13), and held fixed: every
    hypothesis is scored with the same one, so the term changes only with the mean response and
    the tones; for noise-only hypotheses it is a constant and their likelihood ratios are the
    periodogram's alone. Its spectrum is floored at :data:`RAMP_FLOOR` of its mean (a differenced
    record without a walk has a zero at DC that an exact whitener would integrate back). A
    record not from rest: the first len(h) samples, whose filter would read unseen samples before
    the record, are left out."""

    def __init__(self, d: np.ndarray, at_rest: bool):
        M, p = d.shape
        u = tukey_shape(M)
        L = int(np.count_nonzero(u[: M // 2] < 1.0))
        nseg = 1 << int(min(RAMP_LOG2_SEG, max(5, math.floor(math.log2(max(M // 8, 32))))))
        self.taps = nseg // 2
        self.M, self.L = M, L
        c = 1.0 - u**2
        self.c_start = c[:L].copy()
        if not at_rest:
            self.c_start[: self.taps] = 0.0
        self.c_end = c[M - L:].copy()
        self.nu = float(self.c_start.sum() + self.c_end.sum())
        self.h = [self._whitener(d[:, j], nseg) for j in range(p)]

    def _whitener(self, x: np.ndarray, nseg: int) -> np.ndarray:
        from scipy.signal import welch
        S = welch(x, nperseg=nseg, window="hann", detrend="constant")[1]
        S = np.maximum(S, RAMP_FLOOR * max(float(np.mean(S)), 1e-300))
        # the whitener's log magnitude -ln(S) / 2 folded to minimum phase through the real cepstrum
        cep = np.fft.irfft(-0.5 * np.log(S), nseg)
        fold = np.zeros(nseg)
        fold[0] = cep[0]
        fold[1:nseg // 2] = 2.0 * cep[1:nseg // 2]
        fold[nseg // 2] = cep[nseg // 2]
        h = np.fft.irfft(np.exp(np.fft.rfft(fold)), nseg)[: self.taps]
        return h / h[0]

    def __call__(self, d: np.ndarray) -> float:
        """l_ramp of the differenced residual ``d`` (M, p)."""
        from scipy.signal import oaconvolve
        if self.nu <= 0:
            return 0.0
        M, L, K = self.M, self.L, self.taps
        total = 0.0
        for j, h in enumerate(self.h):
            x = d[:, j]
            rss = float(self.c_start @ (oaconvolve(x[:L], h)[:L] ** 2))
            a = max(0, M - L - K)
            rss += float(self.c_end @ (oaconvolve(x[a:], h)[M - L - a: M - a] ** 2))
            total += -0.5 * self.nu * math.log(max(rss, 1e-300) / self.nu)
        return total


def tukey_shape(M: int) -> np.ndarray:
    """The taper's shape u (M,), 0..1, before its normalization to sum w^2 = M."""
    from scipy.signal.windows import tukey
    return tukey(M, TAPER) if M > 2 else np.ones(M)


# -- the record's level: what differencing takes out ---------------------------------------------------------
def level_density(model, N: int, slope_sq: np.ndarray | None = None, at_rest: bool = True):
    """What a record of N samples from rest says through its mean: (C (p, p), q (p,), b0 (p,)).

    C: the covariance of the stationary parts' mean over the record, (1/N) [R(0) + sum_{h=1}^{N-1}
    (1 - h/N) (R(h) + R(h)^T)], with R(h) = H F^(h-1) (F P H^T + Gamma J^T) for h >= 1 (the
    augmented system of :meth:`service.model.predict.Predictor.linear_system`, P its stationary
    state covariance) summed in closed form: sum (1 - h/N) F^(h-1) = A1 - A2 / N, A1 = (I - F^(N-1))
    (I - F)^-1, A2 = (I - N F^(N-1) + (N-1) F^N) (I - F)^-2. ``at_rest``: every state starts at 0,
    Cov(s_k, s_l) = [stationary] - F^k P F^T^l, so the mean's covariance loses (1/N^2) v P v^T,
    v = H (I - F^N) (I - F)^-1. The white parts (sensor noise, the quantizer's Delta^2/12, the
    jitter's std_s^2 times ``slope_sq``, the mean squared slope of the mean response) add their
    variance / N. q: the bias walk's variance per sample, b0: Var(b_0). For a stable plant only.
    Two approximations: the actuator nonlinearities are taken at unit gain (a drive clipped by a
    saturation or held in a dead zone passes less of its noise, not more: the spread is, if
    anything, too wide), and the jitter's noise-driven slope is left out of its power (too narrow
    by that part; the mean slope dominates it wherever a jitter is seen)."""
    from scipy.linalg import solve_discrete_lyapunov
    p = model.p
    pr = model.predictor()
    ls = pr.linear_system()
    C = np.zeros((p, p))
    if ls.Gam.shape[1]:
        F, G, H, J = ls.F, ls.Gam, ls.H, ls.J
        n_s = F.shape[0]
        I = np.eye(n_s)
        P = solve_discrete_lyapunov(F, G @ G.T)
        P = 0.5 * (P + P.T)
        Fn1 = np.linalg.matrix_power(F, N - 1)
        Fn = F @ Fn1
        inv = np.linalg.inv(I - F)
        A1 = (I - Fn1) @ inv
        A2 = (I - N * Fn1 + (N - 1) * Fn) @ inv @ inv
        Cr = H @ (A1 - A2 / N) @ (F @ P @ H.T + G @ J.T)
        C = (H @ P @ H.T + J @ J.T + Cr + Cr.T) / N
        if at_rest:
            v = H @ (I - Fn) @ inv
            C = C - v @ P @ v.T / N**2
    q = np.zeros(p)
    b0 = np.zeros(p)
    for eid, kind, *prm in pr._primitives():
        if kind == "white":
            C = C + np.diag(np.broadcast_to(prm[0], (p,))) / N
        elif kind == "jitter" and slope_sq is not None:
            C = C + np.diag(prm[0] * np.broadcast_to(slope_sq, (p,))) / N
        elif kind == "walk":
            q = q + np.broadcast_to(prm[0], (p,))
            b0 = b0 + np.broadcast_to(prm[1], (p,))
    return 0.5 * (C + C.T), q, b0


def level_loglik(mean: np.ndarray, C: np.ndarray, q: np.ndarray, b0: np.ndarray, N: int) -> float:
    """l_level: the Gaussian log-density of the residual's mean m over a record of N samples from
    rest, whose expectation is 0 under the model, with covariance V = C (the stationary parts'
    mean, :func:`level_density`) + Var(b_0) + q (N - 1)(2N - 1) / 6N (the bias walk's mean from
    b_0): -(1/2) [m^T V^-1 m + ln det 2 pi V].

    Why: differencing (:func:`periodogram`) removes the record's level, and with it the
    information a step command gives about a mean effect (a saturation's limit, a dead zone, a
    scale factor set the level the output settles at). For a stationary residual the mean is
    nearly independent of the differences (exactly for white noise; Grenander 1954: the mean is
    the level's efficient estimate), so the two terms add. Under a walk the mean is not
    independent of the differences; the marginal density used here is wider than the
    conditional one, which weighs the level less than it could."""
    p = C.shape[0]
    if N < 2:
        return 0.0
    V = C + np.diag(b0 + q * (N - 1) * (2 * N - 1) / (6.0 * N))
    V = V + np.eye(p) * 1e-300
    c = np.linalg.cholesky(V)
    z = np.linalg.solve(c, np.asarray(mean, float))
    return float(-0.5 * (z @ z) - np.sum(np.log(np.diag(c))) - 0.5 * p * math.log(2 * math.pi))
