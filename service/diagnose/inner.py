"""The inner problem: the likelihood maximized over the free variances of the noise sources, whose
expected periodogram is linear in each (:class:`Inner`), and the profile's crossing of a
threshold (:func:`_crossing`, shared with :mod:`.intervals`)."""

from __future__ import annotations

import math

import numpy as np

from .thresholds import BLIND, CHI2_95


# -- the likelihood over the free variances (inner problem) ---------------------------------------------------
def _inv_logdet(E: np.ndarray):
    """Inverses and ln det of Hermitian positive definite matrices E (nb, p, p); two and three
    outputs in closed form (batched LAPACK calls on 2 x 2 matrices cost ~10x more)."""
    if E.shape[1] == 2:
        a, d, b = E[:, 0, 0].real, E[:, 1, 1].real, E[:, 0, 1]
        # a model whose outputs share one noise source and nothing else (two outputs of one plant,
        # no sensor noise) predicts a singular E: floored, the data's other direction costs a
        # likelihood of ~1e12 times its power instead of a NaN
        det = np.maximum(a * d - (b.real**2 + b.imag**2), 1e-12 * a * d)
        Ei = np.empty_like(E)
        Ei[:, 0, 0], Ei[:, 1, 1] = d / det, a / det
        Ei[:, 0, 1], Ei[:, 1, 0] = -b / det, -np.conj(b) / det
        return Ei, np.log(det)
    if E.shape[1] == 3:
        # three outputs by E = L D L^H in closed form (4-8x faster than batched inv + slogdet on
        # 3 x 3; the adjugate's determinant loses digits as cond^2, this as cond): pivots d1..d3,
        # each floored like the 2 x 2 determinant; E^-1 = M^H D^-1 M, M = L^-1
        d1 = np.maximum(E[:, 0, 0].real, 1e-300)
        l21, l31 = E[:, 1, 0] / d1, E[:, 2, 0] / d1
        e11, e22 = E[:, 1, 1].real, E[:, 2, 2].real
        d2 = np.maximum(e11 - (l21.real**2 + l21.imag**2) * d1, 1e-12 * e11)
        l32 = (E[:, 2, 1] - l31 * np.conj(E[:, 1, 0])) / d2
        d3 = np.maximum(e22 - (l31.real**2 + l31.imag**2) * d1 - (l32.real**2 + l32.imag**2) * d2, 1e-12 * e22)
        m31 = l21 * l32 - l31                                      # M = [[1, 0, 0], [-l21, 1, 0], [m31, -l32, 1]]
        Ei = np.empty_like(E)
        Ei[:, 2, 2] = 1.0 / d3
        Ei[:, 1, 1] = 1.0 / d2 + (l32.real**2 + l32.imag**2) / d3
        Ei[:, 0, 0] = 1.0 / d1 + (l21.real**2 + l21.imag**2) / d2 + (m31.real**2 + m31.imag**2) / d3
        Ei[:, 0, 1] = -np.conj(l21) / d2 - np.conj(m31) * l32 / d3
        Ei[:, 0, 2] = np.conj(m31) / d3
        Ei[:, 1, 2] = -np.conj(l32) / d3
        Ei[:, 1, 0], Ei[:, 2, 0], Ei[:, 2, 1] = np.conj(Ei[:, 0, 1]), np.conj(Ei[:, 0, 2]), np.conj(Ei[:, 1, 2])
        return Ei, np.log(d1) + np.log(d2) + np.log(d3)
    return np.linalg.inv(E), np.linalg.slogdet(E)[1]


class Inner:
    """l(v) = -sum_b G_b sum_j [ln E_bj + I_bj / E_bj] + l_mod(v_jitter), E = E0 + sum_a v_a U_a,
    v_a >= 0, maximized by projected Fisher scoring (the expected information
    sum_b G_b U_a U_b / E^2 is positive definite, so each step is a Newton-like ascent step).

    Several outputs: I_b, E0_b and U_a,b are p x p cross-spectral matrices (complex Hermitian) and
    l(v) = -sum_b G_b [ln det E_b + tr(E_b^-1 I_b)], the multivariate Whittle likelihood (Whittle
    1953; Brillinger 1981 ch. 7): outputs that share noise (two sensors of one plant) are not
    counted as independent evidence. Score tr(E^-1 U_a E^-1 (I - E)), information
    tr(E^-1 U_a E^-1 U_b)."""

    def __init__(self, I, G, E0, U, mod=None, mod_index=None):
        # G: bins per group divided by the taper's kappa (see :func:`.whittle.loglik`)
        self.multi = I.ndim == 3
        self.I, self.G, self.E0 = I, G.reshape((-1,) + (1,) * (I.ndim - 1)), E0
        self.U = np.stack(U) if len(U) else np.zeros((0,) + I.shape)
        self.Uf = self.U.reshape(len(self.U), I.size)   # the sources' parts as rows (bins x p x p)
        self.mod, self.mod_index = mod, mod_index
        tr = (lambda A: np.einsum("...ii->...", A).real) if self.multi else (lambda A: A)
        tot = float(np.sum(self.G * tr(I)))
        # a source these data cannot see (a noise behind a saturation that clips the whole record:
        # its part is 0, or rounding of 1e-40 that need not even be positive definite) would take a
        # variance 1e30 times its reference to carry their power: held where it starts (its part
        # zeroed, no score, no information), not run up to 1e290 where E overflows
        power = np.array([float(np.sum(self.G * tr(u))) for u in self.U])
        blind = ~(power > BLIND * tot)
        if blind.any():
            self.U = self.U.copy()
            self.U[blind] = 0.0
            self.Uf = self.U.reshape(len(self.U), I.size)
        self.blind = blind
        self.vref = np.where(blind, 1.0, tot / np.where(blind, 1.0, power))
        self.hi = np.where(blind, np.inf, self.vref * 1e4)
        level = E0 + np.tensordot(self.vref, self.U, axes=1) if len(self.U) else E0
        # an output's expected power that rounds to <= 0 is set to 1e-12 of its mean over the bins:
        # a part summed from exponentials of nearly equal modes (a long-memory noise through an
        # integrator) can, where the model has next to no power; data there then cost a very low
        # likelihood instead of a NaN. Positive values, however small (the DC bin of a long
        # record), are kept as they are.
        diag = np.einsum("bii->bi", level).real if self.multi else level
        self.floor = 1e-12 * np.mean(np.abs(diag), axis=0) + 1e-150
        if self.multi:
            p = I.shape[1]
            self.Gb = self.G[:, 0, 0]
            # a ridge of 1e-13 of the mean output power (and a floor) keeps E invertible where a
            # source's spectrum is singular (two outputs of one mode, no sensor noise)
            self.ridge = (1e-13 * np.einsum("bii->b", level).real / p + 1e-150)[:, None, None] * np.eye(p)

    def _E(self, v):
        E = self.E0 + (v @ self.Uf).reshape(self.U.shape[1:]) if len(v) else self.E0
        if self.multi:
            E = E + self.ridge
            d = np.einsum("bii->bi", E)              # a view of the new array's diagonals
            low = d.real <= 0
            if low.any():
                d[low] = np.broadcast_to(self.floor, d.shape)[low]
            return E
        # (positive values at least 1e-150: E**2 stays a normal float)
        return np.where(E > 0, np.maximum(E, 1e-150), self.floor)

    def value(self, v):
        v = np.asarray(v, float)
        E = self._E(v)
        if self.multi:
            Ei, logdet = _inv_logdet(E)
            EiI = Ei @ self.I
            l = -float(self.Gb @ (logdet + np.einsum("bii->b", EiI).real))
            R = (EiI - np.eye(E.shape[1])) @ Ei                      # E^-1 (I - E) E^-1
            # tr(U_a R) with U_a and R Hermitian: sum_ij U_ij conj(R_ij)
            g = (self.Uf @ (np.conj(R) * self.Gb[:, None, None]).ravel()).real
        else:
            l = -float(np.sum(self.G * (np.log(E) + self.I / E)))
            R = self.G * (self.I - E) / E**2
            g = self.Uf @ R.ravel()
        if self.mod is not None:
            lm, gm = self.mod(v[self.mod_index])
            l += lm
            g[self.mod_index] += gm
        return l, g

    def _info(self, v):
        E = self._E(v)
        n = len(self.U)
        F = np.empty((n, n))
        if self.multi:
            Ei = _inv_logdet(E)[0]
            # F_ab = sum_b G_b tr(V_a V_b), V_a = E^-1 U_a: one product over (sources, bins x p x p)
            V = np.matmul(Ei[None], self.U)
            Fc = ((V * self.Gb[:, None, None]).reshape(n, -1) @ V.transpose(0, 1, 3, 2).reshape(n, -1).T).real
            F[:] = 0.5 * (Fc + Fc.T)
        else:
            F[:] = (self.Uf * (self.G / E**2).ravel()) @ self.Uf.T
        if self.mod is not None:
            i = self.mod_index
            h = max(abs(v[i]) * 1e-3, self.vref[i] * 1e-9)
            g1 = self.mod(v[i] + h)[1]
            g0 = self.mod(max(v[i] - h, 0.0))[1]
            F[i, i] += max(-(g1 - g0) / (h + min(h, v[i])), 0.0)
        return F

    def optimize(self, v0=None, fixed: dict | None = None):
        """Maximize over v >= 0 (``fixed``: {index: value} held)."""
        n = len(self.U)
        if n == 0:
            return np.zeros(0), self.value(np.zeros(0))[0]
        fixed = fixed or {}
        starts = [np.clip(self.vref * 1e-2, 0, self.hi)]
        if v0 is not None:
            starts.insert(0, np.clip(np.asarray(v0, float), 0, self.hi))
        for s in starts:
            # a source the data cannot see stays at the model's value (its reference without one)
            s[self.blind] = 1.0 if v0 is None else starts[0][self.blind]
        best = None
        for v in starts:
            v = v.copy()
            for i, x in fixed.items():
                v[i] = x
            l, g = self.value(v)
            for _ in range(100):
                free = np.array([i not in fixed and not (v[i] <= 0 and g[i] <= 0) for i in range(n)])
                if not free.any():
                    break
                F = self._info(v)[np.ix_(free, free)]
                try:
                    step_f = np.linalg.solve(F + 1e-12 * np.trace(F) * np.eye(F.shape[0]) / max(F.shape[0], 1), g[free])
                except np.linalg.LinAlgError:
                    step_f = g[free] / np.maximum(np.diag(F), 1e-300)
                step = np.zeros(n)
                step[free] = step_f
                alpha, improved = 1.0, False
                for _ in range(30):
                    vn = np.clip(v + alpha * step, 0.0, self.hi)
                    ln, gn = self.value(vn)
                    if ln >= l - 1e-12 * abs(l):
                        improved = True
                        break
                    alpha *= 0.5
                if not improved:
                    break
                dl = ln - l
                v, l, g = vn, ln, gn
                if dl < 1e-9 * max(1.0, abs(l)) * 1e-3 and alpha == 1.0:
                    break
            if best is None or l > best[1]:
                best = (v, l)
        return best

    def profile(self, a: int, v_hat: np.ndarray, l_hat: float, chi2: float = CHI2_95):
        """95 % profile interval of v_a (the others re-optimized from ``v_hat``): 2 Delta l <=
        ``chi2``. Each end is bracketed in ln v_a from the estimate, the first step two standard
        errors of ln v_a by the expected information (its inverse's diagonal), the step doubled
        until the profile falls below its threshold, then found by :func:`_crossing` (regula falsi
        on the squared distance from the estimate: 3-4 fits where a bisection to the same 0.02 in l
        took about 30). The lower end is 0 where the profile at 0 stays above the threshold (a
        variance the data do not bound away from 0); the upper stops at 1e4 v_hat (above: the data
        do not bound it). A variance fitted at 0: the lower end 0, the upper searched up by
        decades from 1e-6 of the variance that would carry all the data's power."""
        target = l_hat - chi2 / 2

        def prof(va):
            return self.optimize(v_hat, fixed={a: va})[1]

        vh = float(v_hat[a])
        if not vh > 0:
            inside, l_in, outside = 0.0, l_hat, float(self.vref[a]) * 1e-6
            for _ in range(16):
                l_out = prof(outside)
                if not l_out > target or outside >= self.hi[a]:
                    break
                inside, l_in, outside = outside, l_out, outside * 10.0
            if l_out > target:
                return 0.0, outside
            return 0.0, _crossing(prof, inside, l_in, outside, l_out, target, log=inside > 0)
        try:
            se = math.sqrt(max(float(np.linalg.pinv(self._info(v_hat))[a, a]), 0.0)) / vh
        except (np.linalg.LinAlgError, ValueError):
            se = math.nan
        first = min(max(2.0 * se, 0.01), 2.0) if math.isfinite(se) else 0.5
        far = math.log(1e4)

        def edge(direction):
            inside, l_in, d = vh, l_hat, first
            for _ in range(40):
                if d >= far:
                    # as far as the search goes: 0 below (a variance of none), 1e4 v_hat above
                    outside = 0.0 if direction < 0 else vh * 1e4
                    l_out = prof(outside)
                    if l_out > target:
                        return outside
                    return _crossing(prof, inside, l_in, outside, l_out, target, log=direction > 0,
                                     peak=vh if direction > 0 else None)
                outside = vh * math.exp(direction * d)
                l_out = prof(outside)
                if l_out < target:
                    return _crossing(prof, inside, l_in, outside, l_out, target, peak=vh)
                inside, l_in, d = outside, l_out, 2.0 * d
            return inside

        return edge(-1), edge(1)


def _crossing(l_at, x_in, l_in, x_out, l_out, target, tol=0.02, max_iter=10, log=True, peak=None):
    """Where the profile log-likelihood crosses ``target`` between x_in (above) and x_out (below):
    regula falsi on z = ln x (x > 0; ``log=False``: on x) with the Illinois modification (Dowell &
    Jarratt 1971), to |l - target| < tol (0.04 in 2 Delta l against the 3.84 that defines the edge;
    every step is a full refit, so a bisection's 8 steps cost twice as much for no useful digit).
    ``peak``: the estimate, where the profile is highest, x_in and x_out on one side of it: the
    search then runs on s = (z - z_peak)^2, in which a quadratic profile is a straight line (its
    first step lands on the crossing; on z, a bracket from the peak took 4-5)."""
    fwd, back = (math.log, math.exp) if log else ((lambda v: v), (lambda v: v))
    if peak is not None:
        zp = fwd(peak)
        sign = 1.0 if fwd(x_out) > zp else -1.0

        def to(x):
            return (fwd(x) - zp) ** 2

        def frm(sv):
            return back(zp + sign * math.sqrt(max(sv, 0.0)))
    else:
        to, frm = fwd, back
    a, fa = to(x_in), l_in - target                 # fa > 0
    b, fb = to(x_out), l_out - target               # fb < 0
    side = 0
    for _ in range(max_iter):
        c = b - fb * (b - a) / (fb - fa) if fb != fa else 0.5 * (a + b)
        if not (min(a, b) < c < max(a, b)):
            c = 0.5 * (a + b)
        fc = l_at(frm(c)) - target
        if abs(fc) < tol:
            return frm(c)
        if fc > 0:
            a, fa = c, fc
            if side == -1:
                fb *= 0.5
            side = -1
        else:
            b, fb = c, fc
            if side == 1:
                fa *= 0.5
            side = 1
    return frm(b - fb * (b - a) / (fb - fa)) if fb != fa else frm(0.5 * (a + b))
