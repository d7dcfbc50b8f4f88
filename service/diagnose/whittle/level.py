"""The record's level: what differencing takes out, as a likelihood of the residual's mean."""

from __future__ import annotations

import math

import numpy as np


# -- the record's level: what differencing takes out ---------------------------------------------------------
def level_density(model, N: int, slope_sq: np.ndarray | None = None, at_rest: bool = True):
    """What a record of N samples from rest says through its mean: (C (p, p), q (p,), b0 (p,)).

    C: the covariance of the stationary parts' mean over the record, (1/N) [R(0) + sum_{h=1}^{N-1}
    (1 - h/N) (R(h) + R(h)^T)], with R(h) = H F^(h-1) (F P H^T + Gamma J^T) for h >= 1 (the
    augmented system of :meth:`noiselab.model.predict.Predictor.linear_system`, P its stationary
    state covariance) summed in closed form: sum (1 - h/N) F^(h-1) = A1 - A2 / N, A1 = (I - F^(N-1))
    (I - F)^-1, A2 = (I - N F^(N-1) + (N-1) F^N) (I - F)^-2. ``at_rest``: every state starts at 0,
    Cov(s_k, s_l) = [stationary] - F^k P F^T^l, so the mean's covariance loses (1/N^2) v P v^T,
    v = H (I - F^N) (I - F)^-1. The white parts (sensor noise, the quantizer's Delta^2/12, the
    jitter's std_s^2 times ``slope_sq``, the mean squared slope of the mean response) add their
    variance / N. q: the bias walk's variance per sample, b0: Var(b_0); a walk through the sensor's
    own filter adds its difference from the unfiltered walk's mean to C (:func:`_filtered_walk_mean_excess`).
    For a stable plant only.
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
            if len(prm) > 2 and prm[2] is not None:
                C = C + np.diag(_filtered_walk_mean_excess(prm[2], np.broadcast_to(prm[0], (p,)),
                                                           np.broadcast_to(prm[1], (p,)), N))
    return 0.5 * (C + C.T), q, b0


def _filtered_walk_mean_excess(flt, q: np.ndarray, var0: np.ndarray, N: int) -> np.ndarray:
    """(p,) Var of the mean over N samples from rest of a walk through the sensor's own filter
    ``flt``, less the unfiltered walk's var0 + q (N - 1)(2N - 1) / 6N (which the caller adds).
    With s_m the filter's step response and S_m = sum_(i<=m) s_i, w_k = b_0 s_k + sqrt(q)
    sum_(l<k) eta_l s_(k-l-1), so Var(mean w) = var0 (S_(N-1) / N)^2 + (q / N^2) sum_(m<=N-2) S_m^2
    (s = 1: S_m = m + 1, the unfiltered value)."""
    S = np.cumsum(flt.step_response(N), axis=0)
    exact = var0 * (S[-1] / N) ** 2 + q * np.sum(S[:-1] ** 2, axis=0) / N**2
    return exact - (var0 + q * (N - 1) * (2 * N - 1) / (6.0 * N))


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
