"""Continuous to discrete time (seed lesson section 8).

Symbols -> names used here:

======  ==================  ===========================================================
symbol  name                meaning
======  ==================  ===========================================================
A_c     ``Ac`` (n, n)       continuous state matrix
B_c     ``Bc`` (n, m)       continuous input matrix (input held constant over a sample)
A_d     ``Ad`` (n, n)       discrete state matrix, x_{k+1} = A_d x_k + ...
B_d     ``Bd`` (n, m)       discrete input matrix for a zero-order-held input
Q_c     ``Qc`` (n, n)       continuous two-sided noise intensity L Q_w L^T, units^2 * s
Q_d     ``Qd`` (n, n)       discrete covariance of the noise accumulated over one sample
======  ==================  ===========================================================

Q_d = Q_c is dimensionally wrong (seed section 8); it is never used.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import expm

from ..memo import Memo

_EXPM = Memo(257, flush=True)


def _expm(X: np.ndarray) -> np.ndarray:
    """expm, remembered for the last few hundred arguments (the diagnosis parses many variants of
    one model whose plant does not change, in threads too); a copy, the cached one stays as computed."""
    return _EXPM.get_or_compute((X.shape, X.tobytes()), lambda: expm(X)).copy()


def zoh(Ac: np.ndarray, Bc: np.ndarray, Ts: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretization.

    A_d = e^{A_c Ts},  B_d = int_0^Ts e^{A_c s} ds B_c, both read off one matrix exponential
    expm([[A_c, B_c], [0, 0]] Ts) (Van Loan 1978, sec. 2).
    """
    n, m = Bc.shape
    M = np.zeros((n + m, n + m))
    M[:n, :n] = Ac
    M[:n, n:] = Bc
    E = _expm(M * Ts)
    return E[:n, :n], E[:n, n:]


def euler(Ac: np.ndarray, Bc: np.ndarray, Ts: float) -> tuple[np.ndarray, np.ndarray]:
    """Forward Euler, as in the seed lesson's programs: A_d = I + Ts A_c, B_d = Ts B_c."""
    return np.eye(Ac.shape[0]) + Ts * Ac, Ts * Bc


def van_loan(Ac: np.ndarray, Qc: np.ndarray, Ts: float) -> np.ndarray:
    """Exact Q_d = int_0^Ts e^{A_c s} Q_c e^{A_c^T s} ds (seed eq. in section 8).

    Van Loan (1978), "Computing integrals involving the matrix exponential", Theorem 1:
    expm([[-A_c, Q_c], [0, A_c^T]] h) = [[., F12], [0, F22]], A_d(h) = F22^T, Q_d(h) = A_d(h) F12.
    The block -A_c makes the exponential overflow for stiff models (|A_c| Ts >> 1, e.g. a fast
    actuator lag), so it is evaluated on h = Ts / 2^j with |A_c| h <= 1 and doubled j times:
    Q_d(2h) = Q_d(h) + A_d(h) Q_d(h) A_d(h)^T, A_d(2h) = A_d(h)^2 (the integral split at h).
    """
    n = Ac.shape[0]
    norm = np.linalg.norm(Ac, 1) * Ts
    j = int(max(0, np.ceil(np.log2(norm)))) if norm > 1 else 0
    h = Ts / 2.0**j
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n] = -Ac
    M[:n, n:] = Qc
    M[n:, n:] = Ac.T
    E = _expm(M * h)
    Ad = E[n:, n:].T
    Qd = Ad @ E[:n, n:]
    for _ in range(j):
        Qd = Qd + Ad @ Qd @ Ad.T
        Ad = Ad @ Ad
    return 0.5 * (Qd + Qd.T)


def euler_noise(Qc: np.ndarray, Ts: float) -> np.ndarray:
    """First-order approximation Q_d ~ Q_c Ts (seed section 8), used with ``euler``."""
    return Qc * Ts


def psd_sqrt(Q: np.ndarray) -> np.ndarray:
    """A factor S with S S^T = Q for a symmetric positive semidefinite Q (rank-deficient allowed).

    Columns belonging to zero eigenvalues are dropped, so the number of standard normals drawn per
    sample equals the rank of Q.
    """
    Q = 0.5 * (Q + Q.T)
    w, V = np.linalg.eigh(Q)
    tol = max(w.max(initial=0.0), 0.0) * Q.shape[0] * 1e-13
    keep = w > tol
    return V[:, keep] * np.sqrt(w[keep])
