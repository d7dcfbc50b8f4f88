"""Sums of exponentials: F^h X of a linear system's augmented dynamics, by its eigenvalues."""

from __future__ import annotations

import numpy as np

DECAY = 1e-13            # |lambda|^h below which an exponential's tail is dropped
COND_MAX = 1e8           # eigenvector condition number beyond which F is treated as defective


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
