"""How much a fitted likelihood says: the spread of a likelihood ratio between two fits and the
sandwich (Godambe) variance of a variance whose likelihood overstates its evidence (a modulated
noise: the jitter's, an actuator noise behind a switching gain), from the score's block sums
(Kuensch 1989)."""

from __future__ import annotations

import math

import numpy as np
import scipy.fft as sfft

from ..model.effects import CATALOGUE, of_kind
from ..model.predict import gain_switches
from . import whittle as W
from .data import Data
from .hypotheses import Fit, Hypotheses
from .modulation import Modulation
from .thresholds import CHI2_95, SANDWICH_BLOCK_MIN, SANDWICH_BLOCKS


# -- how far apart two fits of one periodogram are -------------------------------------------------------
def lr_spread(A: Fit, B: Fit) -> float | None:
    """The standard deviation of 2 (l_A - l_B) over records, under A's spectrum, for two fits of the
    same periodogram (None when their residuals differ, e.g. one moves the mean response): the scale
    on which a likelihood ratio between two non-nested models of equal size tells them apart (Vuong
    1989; here model-based, not from the data).

    Only the periodogram is random in l_A - l_B = -sum_b G_b [ln det E_Ab - ln det E_Bb +
    tr((E_Ab^-1 - E_Bb^-1) I_b)]; for a Gaussian transform X of covariance E_A,
    Var(X^H M X) = tr(M E_A M E_A), and a group's mean of n_b ordinates (G_b = n_b / kappa) has
    1 / G_b of one ordinate's variance: Var(l_A - l_B) = sum_b G_b tr[(1 - E_Bb^-1 E_Ab)^2]."""
    ia, ib = A.inner, B.inner
    if ia is None or ib is None or ia.I.shape != ib.I.shape or not np.array_equal(ia.I, ib.I):
        return None
    EA, EB = ia._E(A.v), ib._E(B.v)
    if ia.multi:
        D = np.eye(EA.shape[1]) - np.linalg.solve(EB, EA)
        var = float(ia.Gb @ np.einsum("bij,bji->b", D, D).real)
    else:
        var = float(np.sum(ia.G * (1.0 - EA / EB) ** 2))
    return 2.0 * math.sqrt(max(var, 0.0))


# -- the sandwich variance of a modulated variance --------------------------------------------------------
def score_contributions(H: Hypotheses, fit: Fit) -> np.ndarray:
    """Per-sample terms phi_aq (n, M) of the inner problem's score in each free variance v_a:
    sum_q phi_aq equals the Whittle score sum_b G_b tr(E_b^-1 U_ab E_b^-1 I_b) up to a constant,
    plus the modulation term's.

    With X_f the transform of the tapered differenced residual, the whitened transform
    Y_f = E_f^-1/2 X_f and its series e = irfft(Y): sum_{f < nf} c_f Y_f^H A_f Y_f / M =
    sum_q e_q^T irfft(c A Y)_q, A = E^-1/2 U_a E^-1/2 (c_f = 1/2 inside the half spectrum counts
    its mirror image once; G_b / n_b = 1 / kappa per bin, 1/2 at DC). Whitened, both factors have
    short memory (A lies between 0 and 1 / v_a): unwhitened, U / E^2 grows like 1 / w^2 where a
    differenced spectrum falls like w^2, and the terms would carry that long kernel."""
    d, inner = H.data, fit.inner
    r, ydot = H.ev.grouped_periodogram(fit.model, of_kind(fit.free, "line") is not None)[:2]
    g = np.diff(r[d.k0:], axis=0)
    M = g.shape[0]
    w, _, kappa = W.taper(M)
    X = sfft.rfft(np.ascontiguousarray((g * w[:, None]).T), axis=-1).T      # (M // 2 + 1, p)
    sizes = d.sizes.astype(np.int64)
    E = inner._E(fit.v)
    Y = np.zeros_like(X)
    if inner.multi:
        lam, V = np.linalg.eigh(E)
        Eh = (V / np.sqrt(lam)[:, None, :]) @ np.conj(V.transpose(0, 2, 1))   # E^-1/2 per group
        Y[:d.nf] = np.einsum("fij,fj->fi", np.repeat(Eh, sizes, axis=0), X[:d.nf])
    else:
        Y[:d.nf] = X[:d.nf] / np.repeat(np.sqrt(E), sizes, axis=0)
    e = sfft.irfft(np.ascontiguousarray(Y.T), n=M, axis=-1).T                 # (M, p)
    phi = np.empty((len(fit.v), M))
    for a in range(len(fit.v)):
        Z = np.zeros_like(X)
        if inner.multi:
            A = np.repeat(Eh @ inner.U[a] @ Eh, sizes, axis=0)
            Z[:d.nf] = np.einsum("fij,fj->fi", A, Y[:d.nf])
        else:
            Z[:d.nf] = np.repeat(inner.U[a] / E, sizes, axis=0) * Y[:d.nf]
        Z *= 0.5 / kappa
        phi[a] = np.sum(e * sfft.irfft(np.ascontiguousarray(Z.T), n=M, axis=-1).T, axis=1)
    if inner.mod is not None:
        phi[inner.mod_index] += inner.mod.contributions(g, ydot, d.k0)
    return phi


def godambe_factor(H: Hypotheses, fit: Fit, a: int) -> float:
    """Var(v_a) by the sandwich (Godambe) formula over its model-based value (H^-1)_aa: the factor
    by which a profile-likelihood ratio of v_a overstates its evidence (Chandler & Bate 2007). For
    the jitter, whose Whittle part takes a modulated noise as stationary (its mean power
    varies more: the kurtosis of the modulation) and whose modulation term reads the same squared
    residuals again.

    v_hat - v = H^-1 psi to first order, psi = sum_q phi_q: the influence series
    x_q = sum_i (H^-1)_ai phi_iq (active variances only). Its expected value follows the taper and
    the modulation (w_q^2, x_q, w_q^2 x_q per output: least squares removes it), then the variance
    of its sum is read from :data:`.thresholds.SANDWICH_BLOCKS` block sums (blocks much longer than the
    dependence of a white-like score)."""
    inner = fit.inner
    n = len(fit.v)
    act = [a] + [i for i in range(n) if i != a and fit.v[i] > 0]
    F = inner._info(fit.v)[np.ix_(act, act)]
    try:
        Fi = np.linalg.inv(F)
    except np.linalg.LinAlgError:
        return 1.0
    phi = score_contributions(H, fit)
    infl = Fi[0] @ phi[act]
    M = infl.size
    w2 = W.taper(M)[0] ** 2
    cols = [np.ones(M), w2]
    if inner.mod is not None:
        x = Modulation.slope_squares(H.ev.grouped_periodogram(fit.model, of_kind(fit.free, "line") is not None)[1], H.data.k0)
        for j in range(x.shape[1]):
            xj = x[:, j] / max(float(np.mean(x[:, j])), 1e-300)
            cols += [xj, w2 * xj]
    if any(_behind_nonlinearity(fit.model, e) for e in set(fit.scale_ids)):
        # a noise behind a switching gain: the score's mean follows the squared gain (the power
        # passed), a deterministic pattern whose block sums are not the score's spread
        for gj in _gain_squares(fit.model, H.data, M):
            cols += [gj, w2 * gj]
    B = np.stack(cols, axis=1)
    coef = np.linalg.lstsq(B, infl, rcond=None)[0]
    res = infl - B @ coef
    nb = min(SANDWICH_BLOCKS, M // SANDWICH_BLOCK_MIN)
    if nb < 16:
        return 1.0
    L = M // nb
    S = res[:nb * L].reshape(nb, L).sum(axis=1)
    K = float(np.sum(S**2)) * nb / (nb - 1) * M / (nb * L)
    return K / Fi[0, 0]


def gated(model, eid: str, data: Data) -> bool:
    """Whether ``eid`` is an actuator noise that reaches the plant through a gain that switches over
    the record (a saturation or a dead zone the command reaches part of the time:
    :func:`noiselab.model.predict.gain_switches`): its power arrives modulated, and the stationary
    likelihood takes its periodogram as less spread than it is (the modulation's kurtosis: a noise
    clipped a third of the time has 1.5x the variance in its mean power). Its interval is adjusted
    by :func:`godambe_factor`, as the jitter's. The gain over ``data``'s command (an external
    command's record has one the model's own command does not)."""
    return _behind_nonlinearity(model, eid) and bool(np.any(gain_switches(_gains(model, data))))


def _behind_nonlinearity(model, eid: str) -> bool:
    """An actuator noise of a model with a saturation or a dead zone."""
    return hasattr(model.effects.get(eid), "drive_linear") and any(hasattr(e, "knots") for e in model.effects.values())


def _gains(model, data: Data) -> np.ndarray:
    """The nonlinearities' Bussgang gain (N, m) over the record's command."""
    pr = model.predictor()
    N = data.N
    u = np.asarray(data.u if data.u is not None else model.command.values(0, N, model.Ts), float).reshape(N, -1)
    return pr.drive_stats(u, pr.drive_noise_var(N))[1]


def _gain_squares(model, data: Data, M: int) -> list:
    """The squared gain of each input whose gain switches, over the last M samples of the record
    (the differenced residual's), relative to its mean."""
    g = _gains(model, data)[-M:]          # a gain that switches only before the residual starts: none
    return [g[:, j] ** 2 / np.mean(g[:, j] ** 2) for j in np.flatnonzero(gain_switches(g))]


def _scale_chi2(H: Hypotheses, fit: Fit, eid: str, a: int) -> float:
    """The profile threshold of variance ``a`` (``eid``'s): 3.84, times the sandwich factor (never
    below 1) for a variance whose likelihood overstates its evidence: the jitter's (modulated by the
    slope) and an actuator noise's behind a switching gain (:func:`gated`)."""
    if CATALOGUE[eid].fit.kind == "modulated" or gated(fit.model, eid, H.data):
        return CHI2_95 * max(godambe_factor(H, fit, a), 1.0)
    return CHI2_95
