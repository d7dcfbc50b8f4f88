"""Lyapunov solutions of the augmented system, with a plant's integrator modes set apart.

The stationary covariance of s_{k+1} = F s_k + Gamma e_k, e_k ~ N(0, I), solves the discrete
Lyapunov equation P = F P F^T + Gamma Gamma^T (seed section 4). A plant that integrates (its
continuous A has an eigenvalue 0, so F has one at 1) has none: its unit modes are leaked to
1 - LEAK (:func:`leak_unit_modes`), and the equation is solved with those modes apart
(:func:`lyap_leaky`), so that the increments of the output (its variogram) are the exact walk's.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import solve_discrete_lyapunov


def _powers_apply(F: np.ndarray, X: np.ndarray, L: int) -> np.ndarray:
    """F^d X for d = 0..L-1 by doubling: log2(L) batched products."""
    out = np.empty((L,) + X.shape)
    out[0] = X
    size, Fp = 1, F.copy()
    while size < L:
        take = min(size, L - size)
        out[size:size + take] = Fp @ out[:take]
        Fp = Fp @ Fp
        size += take
    return out


UNIT_REL = 1e-7        # |lambda| / ||A|| within which a continuous eigenvalue is an integrator's
LEAK = 1e-11            # what the prediction takes from an integrator's eigenvalue per sample


def unit_tol(A: np.ndarray, Ts: float) -> float:
    """|lambda_d - 1| within which a discrete eigenvalue is an integrator's: its continuous
    eigenvalue within UNIT_REL ||A|| of 0 (lambda_d = e^(lambda Ts) ~ 1 + lambda Ts), and never
    below rounding (1e-12)."""
    return max(2.0 * UNIT_REL * float(np.linalg.norm(A, 2)) * Ts, 1e-12)


def leak_unit_modes(F: np.ndarray, A: np.ndarray, Ts: float, leak: float = LEAK):
    """(F with its integrators' eigenvalues set to 1 - ``leak``, an orthonormal basis of their
    invariant subspace (n, u)) when the continuous A has eigenvalues 0 (within UNIT_REL ||A||: a
    pole a million times slower than the plant's fastest dynamics is an integrator to any record)
    that are semisimple (A's nullity, by its singular values at the same tolerance, equals their
    number) and every other eigenvalue of F is inside the unit circle; else None (no integrator,
    an unstable mode, or a chain of integrators, whose increments are not stationary either).
    F is A's discretization (zoh or Euler: an eigenvalue 0 of A is an eigenvalue 1 of F).

    Why a leak: an integrator's output is a random walk plus a stationary part, correlated through
    the noise they share. With the eigenvalue at 1 - eps every source has a stationary covariance
    (its walk part ~ q / (2 eps)), and every statistic the diagnosis uses from it, increments and
    differences (variogram, differenced-output spectrum), is the exact walk's to a relative
    O(eps d) at lag d (1e-5 at 10^6), provided they are formed from (I - F) P
    (:func:`lyap_leaky`), not as differences of covariances at the walk's scale."""
    if F.size == 0:
        return None
    from scipy.linalg import schur
    nA = float(np.linalg.norm(A, 2))
    tolA = UNIT_REL * nA
    uA = int(np.sum(np.abs(np.linalg.eigvals(A)) <= tolA)) if nA > 0 else A.shape[0]
    if uA == 0:
        return None
    null = int(np.sum(np.linalg.svd(A, compute_uv=False) <= tolA)) if nA > 0 else A.shape[0]
    if null != uA:                      # a chain of integrators (a double integrator)
        return None
    T, Z, u = schur(F, output="real", sort=lambda re, im: abs(complex(re, im) - 1.0) <= unit_tol(A, Ts))
    lam = np.linalg.eigvals(T[u:, u:]) if u < F.shape[0] else np.zeros(0)
    if u != uA or np.any(np.abs(lam) >= 1.0):
        return None
    T = T.copy()
    T[:u, :u] = (1.0 - leak) * np.eye(u)
    return Z @ T @ Z.T, Z[:, :u]


def _decouple(F: np.ndarray, leak: float = LEAK):
    """(S, Si, T11, T22, u): F = S diag(T11, T22) S^-1 with the u leaked integrator modes
    (:func:`leak_unit_modes`) in T11 and the others in T22: an ordered real Schur form, decoupled
    by a Sylvester solve (T11 X - X T22 = -T12, S = Z [[I, X], [0, I]])."""
    from scipy.linalg import schur, solve_sylvester
    T, Z, u = schur(F, output="real", sort=lambda re, im: abs(complex(re, im) - 1.0) < 2 * leak)
    n = F.shape[0]
    T11, T12, T22 = T[:u, :u], T[:u, u:], T[u:, u:]
    X = solve_sylvester(T11, -T22, -T12) if 0 < u < n else np.zeros((u, n - u))
    Si = np.eye(n)
    Si[:u, u:] = -X
    Si = Si @ Z.T
    S = Z.copy()
    S[:, u:] += Z[:, :u] @ X
    return S, Si, T11, T22, u


def unit_projector(F: np.ndarray, leak: float = LEAK) -> np.ndarray:
    """The spectral projector onto F's leaked integrator modes: Pi F = F Pi = (1 - leak) Pi, so the
    walk's part of the state, Pi x, takes Pi Gamma w_k per sample (Pi Gamma w_k also carries a
    colored source's whole low-frequency gain: its state's effect on the walk is in Pi)."""
    S, Si, _, _, u = _decouple(F, leak)
    return S[:, :u] @ Si[:u]


def lyap_leaky(F: np.ndarray, Q: np.ndarray, leak: float = LEAK) -> tuple[np.ndarray, np.ndarray]:
    """(P, (I - F) P), P = F P F^T + Q, for an F whose integrator modes were leaked to 1 - ``leak``
    (:func:`leak_unit_modes`), solved with those modes apart (:func:`_decouple`): a direct solve's
    conditioning (~1 / (2 leak)) would spread the walk's error ~1e-16 / leak of its size over the
    stable block. The three blocks are solved each at its own conditioning: only the walk's own
    block is ill-conditioned, and its error stays in it."""
    S, Si, T11, T22, u = _decouple(F, leak)
    n = F.shape[0]
    if u == 0:
        P = solve_discrete_lyapunov(F, Q)
        return P, (np.eye(n) - F) @ P
    Qb = Si @ Q @ Si.T
    Pb = np.zeros((n, n))
    Pb[:u, :u] = solve_discrete_lyapunov(T11, Qb[:u, :u])
    if u < n:
        Pb[u:, u:] = solve_discrete_lyapunov(T22, Qb[u:, u:])
        # P12 = T11 P12 T22^T + Q12, column-major vec: (I - T22 (x) T11) vec P12 = vec Q12
        k = np.eye(u * (n - u)) - np.kron(T22, T11)
        P12 = np.linalg.solve(k, Qb[:u, u:].reshape(-1, order="F")).reshape((u, n - u), order="F")
        Pb[:u, u:] = P12
        Pb[u:, :u] = P12.T
    P = S @ Pb @ S.T
    # (I - F) P = S (I - Tb) Pb S^T with the walk's block (I - T11) P11 = leak P11 ~ q / 2 formed
    # without the cancellation (I - F) P would have at the walk's scale
    IT = np.eye(n)
    IT[:u, :u] -= T11
    IT[u:, u:] -= T22
    D = S @ (IT @ Pb) @ S.T
    return 0.5 * (P + P.T), D


def _sensor_lyap(ls, Gj: np.ndarray, plant_part: slice) -> np.ndarray:
    """Lyapunov on the sensor-state block only (used when the plant itself is not stable) of the
    augmented system ``ls`` (a :class:`.predict.LinearSystem`)."""
    n_s = ls.F.shape[0]
    s = slice(plant_part.stop, n_s)
    P = np.zeros((n_s, n_s))
    if s.stop > s.start:
        P[s, s] = solve_discrete_lyapunov(ls.F[s, s], (Gj @ Gj.T)[s, s])
    return P


def _settle_samples(model) -> int:
    """Samples for the plant's transient to decay to ~1e-6 (ln 1e6 ~ 14 time constants)."""
    ev = np.linalg.eigvals(model.Ad)
    ev = np.abs(ev[np.abs(ev - 1.0) > unit_tol(model.Ac, model.Ts)])   # an integrator's never settles: the others
    r = np.max(ev, initial=0.0)
    if r >= 1.0 or r == 0.0:
        return 0
    return int(min(np.ceil(14.0 / -np.log(r)), 10**7))
