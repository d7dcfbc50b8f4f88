"""Statistical linearization of the static actuator nonlinearities (seed section 7).

A static nonlinearity N (dead zone, saturation: piecewise linear) is linearized around the mean
drive: the mean drive is E[N(u)] and the noise passes with gain g_k = E[N'(u)], u ~ N(u_c,k, s_k^2);
the rest, the distortion d = N(u) - E[N] - g n, is uncorrelated with the noise n (Bussgang) and
enters as a noise of its own, owned by the nonlinearity. The Gaussian expectations of a
piecewise-linear map are exact in closed form (:func:`gauss_pwl`). Where the actuator noise is
colored, the gain's fluctuation over the command (:meth:`Linearization._gain_shadows`) and the
distortion's color (:meth:`Linearization._distortion_colors`) are fitted by damped cosines.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import solve_discrete_lyapunov
from scipy.special import ndtr

from ..memo import Memo
from .lyapunov import _powers_apply
from .mean_response import MeanResponse, mean_key
from .spectra import _damped_cosines, _lag_products

_SQRT2PI = np.sqrt(2.0 * np.pi)

DISTORTION_TERMS = 20     # Hermite terms of a colored noise's distortion (Predictor._distortion_colors)

# The gain fluctuation's and the distortion's damped-cosine fits of a nonlinear model, by the same
# key as the model's own mean response (predict._OWN_MEAN; they depend on nothing else): (shadow,
# dcolor) of Predictor._colors. Not to be changed by callers.
_COLORS = Memo(65, flush=True)


# -- Gaussian expectations of piecewise-linear maps (statistical linearization) ---------------------
def pwl_pieces(fn, b: np.ndarray):
    """A piecewise-linear map ``fn`` with kinks ``b`` (sorted, unique): the points
    ext = [b_0 - pad, b, b_-1 + pad], fn(ext) and the slopes of the K + 1 pieces. The map is linear
    beyond its outer kinks, so any step past them gives the outer slopes; pad = max(1, max |b|) is
    one that float64 does not lose (b +- 1 rounds to b beyond 2^53, and the slope would be 0 / 0)."""
    pad = max(1.0, float(np.max(np.abs(b))))
    ext = np.concatenate([[b[0] - pad], b, [b[-1] + pad]])
    fv = fn(ext)
    return ext, fv, np.diff(fv) / np.diff(ext)


def gauss_pwl(fn, knots: np.ndarray, mu: np.ndarray, sigma: np.ndarray, *, second: bool = False):
    """E[f(U)] and E[f'(U)] (and E[f(U)^2] with ``second``) for U ~ N(mu, sigma^2), f piecewise
    linear with kinks at ``knots``.

    Exact, in closed form on each linear piece a + s u over [lo, hi] (z = (u - mu)/sigma, alpha and
    beta the standardized ends): int phi = dPhi, int z phi = phi(alpha) - phi(beta),
    int z^2 phi = dPhi + alpha phi(alpha) - beta phi(beta). sigma = 0 gives f(mu), f'(mu), f(mu)^2.
    Neighbouring pieces share their ends: the normal's cdf and pdf are taken once per knot, the
    knots along the first axis (rows of the whole record: a reduction over a short last axis costs
    numpy more than the arithmetic).
    """
    b = np.unique(np.asarray(knots, float))
    ext, fv, slope = pwl_pieces(fn, b)
    slope = slope[:, None]                                  # K+1 pieces
    # each piece's intercept from its end nearer 0: from a far end (a saturation at 1e20 beside a
    # dead zone of 0.01) f - s x cancels to rounding of 1e20 and the dead zone's offset is lost
    near = np.where(np.abs(ext[:-1]) <= np.abs(ext[1:]), 0, 1) + np.arange(ext.size - 1)
    icpt = fv[near, None] - slope * ext[near, None]
    mu, sg = np.broadcast_arrays(np.asarray(mu, float), np.asarray(sigma, float))
    shape = mu.shape
    mu, sg = mu.ravel(), sg.ravel()
    pos = sg > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        z = (b[:, None] - mu) / sg                          # the knots standardized (K, n)
    degenerate = not pos.all()
    if degenerate:                                          # sigma = 0: a step at the knot
        z = np.where(pos, z, np.where(b[:, None] <= mu, -np.inf, np.inf))
    phi = np.exp(-0.5 * z * z) / _SQRT2PI                   # 0 at +-inf
    zero = np.zeros((1, mu.size))
    dP = np.diff(np.concatenate([zero, ndtr(z), zero + 1.0]), axis=0)     # (K+1, n) per piece
    dphi = np.diff(np.concatenate([zero, phi, zero]), axis=0)             # phi(beta) - phi(alpha)
    gain = (slope * dP).sum(axis=0)
    mean = (icpt * dP).sum(axis=0) + mu * gain - sg * (slope * dphi).sum(axis=0)
    if not second:
        return mean.reshape(shape)[()], gain.reshape(shape)[()]
    with np.errstate(invalid="ignore"):
        zphi = z * phi
    if degenerate:
        zphi = np.where(np.isfinite(z), zphi, 0.0)
    e_z2 = dP - np.diff(np.concatenate([zero, zphi, zero]), axis=0)       # int z^2 phi
    lin = icpt + slope * mu                                 # a + s u = lin + s sigma z on the piece
    sq = (lin * lin * dP - 2.0 * sg * (lin * slope) * dphi + (slope * slope) * (sg * sg) * e_z2).sum(axis=0)
    return mean.reshape(shape)[()], gain.reshape(shape)[()], sq.reshape(shape)[()]


def gain_switches(gain: np.ndarray) -> np.ndarray:
    """Per input (m,): whether the nonlinearity's gain (N, m) fluctuates over the record: its
    variance a visible share of its mean square, and of the source's own power (the gain is at most
    1: a saturation that clips the whole record leaves gains of 1e-68, whose fluctuation's
    spectrum is all underflow)."""
    c0 = np.var(gain, axis=0)
    return (c0 > 1e-6 * np.mean(gain**2, axis=0)) & (c0 > 1e-12)


class Linearization:
    """The statistical linearization of a :class:`.predict.Predictor`'s actuator nonlinearities
    (a mixin): its ``model``, ``horizon``, ``_nonlin`` (the nonlinear effects) and
    ``_act_blocks`` (the actuator sources' (F, G, C, D))."""

    def _nonlinear(self, u: np.ndarray) -> np.ndarray:
        for e in self._nonlin:
            u = e.apply(u)
        return u

    def _channel_map(self, j: int):
        """(f, knots): input channel j's nonlinearities composed, as a map of one array, and their kinks."""
        knots = np.concatenate([e.knots()[j] for e in self._nonlin])

        def fj(v):
            arr = np.zeros((v.size, self.model.m))
            arr[:, j] = v
            return self._nonlinear(arr)[:, j]
        return fj, knots

    def drive_stats(self, u_c: np.ndarray, var: np.ndarray):
        """Mean drive E[N(u_c + n)], gain g = E[N'(u_c + n)] and distortion variance
        Var(N) - g^2 var, for n ~ N(0, var), per channel (Bussgang: N(u) = E[N] + g n + d with d
        uncorrelated with n)."""
        if not self._nonlin:
            return u_c.copy(), np.ones_like(u_c), np.zeros_like(u_c)
        mean = np.empty_like(u_c)
        gain = np.empty_like(u_c)
        dvar = np.empty_like(u_c)
        sd = np.sqrt(np.broadcast_to(var, u_c.shape))
        for j in range(self.model.m):
            fj, knots = self._channel_map(j)
            mean[:, j], gain[:, j], sq = gauss_pwl(fj, knots, u_c[:, j], sd[:, j], second=True)
            dvar[:, j] = np.maximum(sq - mean[:, j] ** 2 - gain[:, j] ** 2 * sd[:, j] ** 2, 0.0)
        return mean, gain, dvar

    def _colors(self, mean: MeanResponse, burn: int, dstd: np.ndarray):
        """(:meth:`_gain_shadows`, :meth:`_distortion_colors`) of the own mean after ``burn``,
        shared through :data:`_COLORS` by the models that share the mean response (a diagnosis
        varies the other effects' parameters thousands of times; these fits were a third of a
        nonlinear model's steady state)."""
        mdl = self.model
        # the fitting functions in the key too: a predictor given other ones (a test's "before")
        # does not take the shared fits
        fits = tuple(getattr(f, "__func__", f) for f in (self._gain_shadows, self._distortion_colors))
        key = (mean_key(mdl), self.horizon, fits)

        def compute():
            u = mdl.command.values(0, mean.t.size, mdl.Ts)[burn:].reshape(-1, mdl.m)
            return self._gain_shadows(mean.gain[burn:]), self._distortion_colors(u, dstd**2)
        return _COLORS.get_or_compute(key, compute)

    def _source_acf(self, i: int, D: int) -> np.ndarray:
        """Autocovariance (D + 1, m) of actuator source i per input channel at lags 0..D:
        C F^(d-1) (F Pa C^T + G D^T) for d >= 1, C Pa C^T + D D^T at 0 (Pa its stationary covariance)."""
        Fi, Ga, Ci, Da = self._act_blocks[i]
        Rn = np.zeros((D + 1, self.model.m))
        Rn[0] = np.diag(Da @ Da.T)
        if Fi.shape[0] == 0:
            return Rn
        Pa = solve_discrete_lyapunov(Fi, Ga @ Ga.T)
        Rn[0] += np.diag(Ci @ Pa @ Ci.T)
        X = Fi @ Pa @ Ci.T + Ga @ Da.T
        if D:
            Rn[1:] = np.diagonal(np.einsum("ij,djk->dik", Ci, _powers_apply(Fi, X, D)), axis1=1, axis2=2)
        return Rn

    def _distortion_colors(self, u: np.ndarray, dvar: np.ndarray) -> dict:
        """The color of the nonlinearities' distortion where the actuator noise is colored.

        With n_k Gaussian, std s and correlation rho(d) (all sources of the channel) and f the
        channel's piecewise-linear map, Mehler's formula gives
        Cov(f(u_k + n_k), f(u_l + n_l)) = sum_(j>=1) c_j(k) c_j(l) rho^j / j!, c_j(k) the Hermite
        coefficients of z -> f(u_k + s z). The j = 1 term is the gain's (g_k g_l R_n: the rms
        gain and :meth:`_gain_shadows`); the rest is the distortion's. Two Stein steps give, at the
        kinks x_i (slope change Delta_i, z_ik = (x_i - u_k) / s),
        c_j(k) = s sum_i Delta_i phi(z_ik) He_(j-2)(z_ik), j >= 2, so the distortion's
        autocovariance over the command is D(d) = sum_(j>=2) mean_k[c_j(k) c_j(k+d)] rho(d)^j / j!
        (normalized Hermite functions up to DISTORTION_TERMS; the remainder of its variance
        decays as the last term's). For white noise rho(d) = 0 at d >= 1 and D is white; for an
        AR(1) slower than the sample D(d) follows it (rho^2, rho^3, ...), far from white. D is
        fitted by damped cosines and a white part (:func:`_damped_cosines`), per channel.
        ``u`` (N, m): the command after the transient; ``dvar`` (m,): the mean distortion variance.
        {channel: (white variance, [block (F, G, C, D)])} for the channels with colored noise."""
        out: dict = {}
        N, m = u.shape
        Ts = self.model.Ts
        rads = [float(np.max(np.abs(np.linalg.eigvals(b[0])))) if b[0].shape[0] else 0.0 for b in self._act_blocks]
        colored = [i for i, r in enumerate(rads) if 0.0 < r < 1.0]
        if N < 4 or not colored:
            return out
        rad = max(rads[i] for i in colored)
        # the distortion decays at least as rho^2: lags to 1e-9 of its variance
        D = int(min(N - 1, np.ceil(np.log(1e-9) / (2 * np.log(rad))) + 1))
        Rn = sum((self._source_acf(i, D) for i in range(len(self._act_blocks))), np.zeros((D + 1, m)))
        J = DISTORTION_TERMS
        jj = np.arange(2, J + 1)
        for ch in range(m):
            s2 = Rn[0, ch]
            if s2 <= 0 or dvar[ch] <= 1e-12 * s2 or abs(Rn[1, ch]) < 0.05 * s2:
                continue            # no distortion, or a noise so nearly white that its distortion is white
            s = np.sqrt(s2)
            rho = Rn[:, ch] / s2
            fj, knots = self._channel_map(ch)
            b = np.unique(knots)
            slope = pwl_pieces(fj, b)[2]
            delta = np.diff(slope)                                  # the slope's change at each kink
            # (K, N), clipped at 40 std: phi(40) = exp(-800) is 0 in float64 as it is beyond, and the
            # Hermite functions stay finite (40^19); unclipped, a kink 1e16 std away gives 0 * inf
            z = np.clip((b[:, None] - u[:, ch]) / s, -40.0, 40.0)
            wphi = s * delta[:, None] * np.exp(-0.5 * z * z) / _SQRT2PI
            # c_j / sqrt(j!) = s sum_i Delta_i phi h_(j-2)(z) / sqrt(j (j - 1)), h_n = He_n / sqrt(n!)
            cj = np.empty((J - 1, N))
            h0, h1 = np.ones_like(z), z.copy()
            for n in range(J - 1):
                cj[n] = (wphi * h0).sum(axis=0) / np.sqrt((n + 2) * (n + 1))
                h0, h1 = h1, (z * h1 - np.sqrt(n + 1) * h0) / np.sqrt(n + 2)
            M = _lag_products(cj.T, D)                              # (D + 1, J - 1)
            Dd = (M * rho[:, None] ** jj).sum(axis=1)
            rem = max(float(dvar[ch]) - float(M[0].sum()), 0.0)
            if M[0, -1] > 0:
                Dd += rem * rho ** (J + 1) * M[:, -1] / M[0, -1]
            else:
                Dd[0] += rem
            if Dd[0] <= 0:
                continue
            out[ch] = _damped_cosines(Dd, rad, N, Ts, ch, m, white=True)
        return out

    def _gain_shadows(self, gain: np.ndarray) -> dict:
        """The gain fluctuation's part of each colored actuator source, for :meth:`linear_system`.

        Through a nonlinearity the source n_k reaches the plant as g_k n_k (Bussgang), g_k the
        gain at sample k of the command (0 in a saturation, 1 outside). Over time the product's
        autocovariance is R_g(d) R_n(d), R_g(d) = mean_k g_k g_(k+d) (the gain is the command's,
        independent of the noise): the rms gain on the source's own spectrum is right only at
        d = 0, and too narrow a spectrum when the gain switches within the noise's correlation
        time (a chirp through the limit). Split R_g(d) = gbar^2 + c(d): the mean gain keeps the
        source's own spectrum, and the fluctuation's part h(d) = c(d) R_n(d) is a sum of at most
        :data:`SHADOW_BLOCKS` damped cosines w r^|d| cos(theta d) (a rotating AR(1) of two
        states; theta = 0: an AR(1)), weights w >= 0 fitted to h's spectrum by non-negative least
        squares in relative error on frequencies log-spaced from the horizon's lowest to Nyquist,
        the variance sum w = h(0) held exactly (gbar^2 + c(0) = mean g^2, as with the rms gain).
        Poles r from the source's slowest to about 1/20 (a few samples), theta from 0 to Nyquist.
        Per input channel; any source with states (a white one is exact with the rms gain).
        ``gain`` (N, m) over the model's own command after its transient.
        {source index: (gbar (m,), [block (F, G, C, D)])}."""
        out: dict = {}
        N = gain.shape[0]
        if N < 4:
            return out
        mdl = self.model
        Ts, m = mdl.Ts, mdl.m
        gbar = gain.mean(axis=0)
        dev = gain - gbar
        # the fluctuation is worth more blocks only where the gain switches (:func:`gain_switches`)
        active = gain_switches(gain)
        for i, (Fi, Ga, Ci, Da) in enumerate(self._act_blocks):
            if Fi.shape[0] == 0:
                continue
            rad = float(np.max(np.abs(np.linalg.eigvals(Fi))))
            if not active.any() or not 0.0 < rad < 1.0:
                continue
            D = int(min(N - 1, np.ceil(np.log(1e-9) / np.log(rad)) + 1))
            Rn = self._source_acf(i, D)
            comps = []
            for j in np.flatnonzero(active & (Rn[0] > 0)):
                comps += _damped_cosines(_lag_products(dev[:, j:j + 1], D)[:, 0] * Rn[:, j], rad, N, Ts, j, m)[1]
            if comps:
                out[i] = (gbar, comps)
        return out

    def _distortion_owner(self) -> str:
        """The effect id the distortion is reported under: the (first) nonlinearity."""
        return self._nonlin[0].id
