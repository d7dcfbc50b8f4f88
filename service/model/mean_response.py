"""The mean response (seed section 3): m_{k+1} = A_d m_k + B_d E[drive_k], E[y_k] = (1 + s_f)(C m_k +
D E[drive_k]), the drive's statistics through the actuator nonlinearities, and the free response
of a record that does not start at rest."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import block_diag, solve_discrete_lyapunov

from .effects import CATALOGUE
from .lyapunov import _powers_apply
from .simulate import lsim


@dataclass
class MeanResponse:
    t: np.ndarray           # (N,) s
    x: np.ndarray           # (N, n_x) mean continuous-stage state
    drive: np.ndarray       # (N, m) mean plant input E[N(u_c + n_a)]
    gain: np.ndarray        # (N, m) statistical-linearization gain of the actuator nonlinearities
    drive_var: np.ndarray   # (N, m) variance of the actuator noise before the nonlinearities
    distortion_var: np.ndarray  # (N, m) variance of the nonlinearities' distortion d (Bussgang)
    ydot: np.ndarray        # (N, p) mean derivative of the plant output
    y: np.ndarray           # (N, p) predicted mean measurement


@dataclass(frozen=True)
class HorizonAverages:
    """Averages of the model's own mean response over the horizon's samples k = burn..n-1, per
    output, for the steady state's signal-dependent terms."""
    burn: int                       # samples left out at the start (the plant's transient)
    ydot2: np.ndarray               # mean of E[ydot_k]^2 (the jitter's slope)
    y_var: np.ndarray               # variance of E[y_k] over the samples (the quantizer's spread)
    span_s: float                   # time from the first sample averaged to the last, s


def mean_key(model, gain: bool = True) -> str:
    """The part of a model the mean response depends on: plant, sampling, command and the mean
    effects; actuator noise only through the nonlinearities' statistical linearization.
    ``gain=False``: without the sensor gain (the scale factor)."""
    d = model.to_dict()
    if not gain:
        d.get("sensor", {}).pop("scale_factor", None)
    nonlin = any(hasattr(e, "knots") for e in model.effects.values())
    for g in ("process", "sensor", "actuator"):
        sub = d.get(g, {})
        for s in list(sub):
            eid = f"{g}.{s}"
            if CATALOGUE[eid].fit.kind != "mean" and not (nonlin and g == "actuator"):
                sub.pop(s)
    d.pop("description", None)
    d.pop("name", None)
    return repr(d)


def free_response_fit(model, y: np.ndarray, ym: np.ndarray, yd: np.ndarray, k0: int,
                      gain: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """For a record that does not start at rest under a command (cut mid-stream, or the longest
    run after a gap): the mean response of its command starts from zero at sample 0, the plant (and
    an actuator lag) did not. The unknown mean state at sample ``k0`` is fitted to y - ym on
    samples k0.. by least squares, one regressor per state (the free response Cy Ad^j e_i, times
    ``gain`` per output: the sensor gain when ym has it), and its free response is added to the
    mean ym and to its slope yd (Cy Ac Ad^j x). Returns new arrays (N, p); before k0 they are ym
    and yd. The burn before k0 leaves the modes that decay slowly; without it a fast plant's
    transient, 10 % of the command's response after the burn, stayed far above a small noise."""
    y = np.asarray(y, float).reshape(len(y), -1)
    N, p = y.shape
    n = N - k0
    ym, yd = np.array(ym, float), np.array(yd, float)
    if model.n_x == 0 or n <= model.n_x:
        return ym, yd
    g = np.ones(p) if gain is None else np.broadcast_to(np.asarray(gain, float), (p,))
    C = np.vstack([model.Cy, model.Cy @ model.Ac])
    # the free response only where it is not yet rounding (a stable plant's: up to rho^K = 1e-16)
    rho = float(np.max(np.abs(np.linalg.eigvals(model.Ad))))
    K = n if rho >= 1.0 - 1e-12 else min(n, int(np.ceil(np.log(1e-16) / np.log(max(rho, 1e-300)))) + 1)
    imp = np.zeros((K + 1, 1))
    imp[0] = 1.0
    basis = np.empty((K, 2 * p, model.n_x))
    for i in range(model.n_x):      # x_1 = e_i from an impulse through Bd = e_i: then Cy Ad^j e_i
        basis[:, :, i] = lsim(model.Ad, np.eye(model.n_x)[:, i:i + 1], C, np.zeros((2 * p, 1)), imp)[1:]
    basis *= np.concatenate([g, g])[None, :, None]
    Phi = basis[:, :p].reshape(K * p, model.n_x)
    x0 = np.linalg.lstsq(Phi, (y[k0:k0 + K] - ym[k0:k0 + K]).ravel(), rcond=1e-10)[0]
    ym[k0:k0 + K] += basis[:, :p] @ x0
    yd[k0:k0 + K] += basis[:, p:] @ x0
    return ym, yd


class MeanResponses:
    """The mean response of a :class:`.predict.Predictor` (a mixin): its ``model``, ``horizon``
    and the actuator sources' blocks ``_Fa``, ``_Ga``, ``_Ca``, ``_Da``; the drive through the
    nonlinearities from ``drive_stats`` (:class:`.linearize.Linearization`)."""

    # -- actuator drive statistics ----------------------------------------------------------------
    def drive_noise_var(self, n: int) -> np.ndarray:
        """Var of the actuator noise n_a,k (before nonlinearities), k = 0..n-1, per channel (n, m):
        diag(C_a Pa_k C_a^T + D D^T) with Pa_0 = 0 (the noise states start at zero) and
        Pa_k = sum_{i<k} F^i G G^T F^i^T, the transient of Pa_{k+1} = F Pa_k F^T + G G^T.

        Computed by doubling, Pa_{s+j} = Pa_s + F^s Pa_j F^s^T (log2 of the transient length in
        batched products, each term a sum of PSD matrices: no cancellation), up to the sample where
        ||F^s||_2^2 < 1e-17; from there on Pa_k equals Pa_s to ~1e-17 relative (Pa_j <= Pa_inf in
        the Loewner order, so F^s Pa_j F^s^T <= ||F^s||^2 Pa_inf) and the rest is filled with it."""
        m = self.model.m
        DD = sum((D @ D.T for D in self._Da), np.zeros((m, m)))
        GG = block_diag(*[G @ G.T for G in self._Ga]) if self._Ga else np.zeros((0, 0))
        F, Ca = self._Fa, self._Ca
        out = np.empty((n, m))
        if n == 0:
            return out
        if F.shape[0] == 0 or not np.any(GG):
            out[:] = np.diag(DD)
        else:
            na = F.shape[0]
            Pa = np.zeros((1, na, na))
            size, S, Fp = 1, GG.copy(), F.copy()       # S = Pa_size, Fp = F^size
            while size < n:
                take = min(size, n - size)
                if Pa.shape[0] < size + take:
                    grown = np.empty((size + take, na, na))
                    grown[:size] = Pa[:size]
                    Pa = grown
                # Pa_{size+j} = Pa_size + F^size Pa_j F^size^T, j = 0..take-1
                Pa[size:size + take] = S + Fp @ Pa[:take] @ Fp.T
                settled = np.linalg.norm(Fp, 2) ** 2 < 1e-17
                if take == size:
                    S = S + Fp @ S @ Fp.T                  # Pa_{2 size}
                    Fp = Fp @ Fp
                size += take
                if settled:
                    break
            K = min(size, n)
            v = np.einsum("ij,kjl,il->ki", Ca, Pa[:K], Ca) + np.diag(DD)
            out[:K] = v
            if K < n:
                out[K:] = np.einsum("ij,jl,il->i", Ca, S, Ca) + np.diag(DD)
        return out

    # -- mean (seed section 3) ------------------------------------------------------------------------
    def mean_response(self, n: int | None = None, command: np.ndarray | None = None) -> MeanResponse:
        """m_{k+1} = A_d m_k + B_d E[drive_k]; E[y_k] = (1+s_f)(C m_k + D E[drive_k]) (seed sec. 3).
        ``command`` (N, m) is a recorded command; default: the model's own command generator."""
        mdl = self.model
        if command is None:
            n = self.horizon if n is None else n
            u = mdl.command.values(0, n, mdl.Ts)
        else:
            u = np.asarray(command, float).reshape(len(command), -1)
            n = u.shape[0]
        var = self.drive_noise_var(n)
        drive, gain, dvar = self.drive_stats(u, var)
        # the states by modal real recursions (Schur propagator when A_d's eigenvectors are ill-conditioned)
        x = lsim(mdl.Ad, mdl.Bd, np.eye(mdl.n_x), np.zeros((mdl.n_x, 0)), drive) if mdl.n_x else np.zeros((n, 0))
        y = (x @ mdl.Cy.T + drive @ mdl.Dy.T) * mdl.out_gain
        ydot = (x @ (mdl.Cy @ mdl.Ac).T + drive @ (mdl.Cy @ mdl.Bc).T) * mdl.out_gain
        return MeanResponse(t=np.arange(n) * mdl.Ts, x=x, drive=drive, gain=gain, drive_var=var,
                            distortion_var=dvar, ydot=ydot, y=y)

    def _mean_block(self, k0: int, n: int, x0: np.ndarray) -> MeanResponse:
        """:meth:`mean_response` of the model's own command at samples k0..k0+n-1, the state
        starting from ``x0`` (the recursion's state at k0), the drive noise's variance at those k
        (:meth:`_drive_noise_var_from`)."""
        mdl = self.model
        u = mdl.command.values(k0, n, mdl.Ts)
        var = self._drive_noise_var_from(k0, n)
        drive, gain, dvar = self.drive_stats(u, var)
        # the forced response from rest (as mean_response) plus the free one of x0: A_d^j x0
        x = lsim(mdl.Ad, mdl.Bd, np.eye(mdl.n_x), np.zeros((mdl.n_x, 0)), drive) \
            + _powers_apply(mdl.Ad, x0[:, None], n)[:, :, 0] if mdl.n_x else np.zeros((n, 0))
        y = (x @ mdl.Cy.T + drive @ mdl.Dy.T) * mdl.out_gain
        ydot = (x @ (mdl.Cy @ mdl.Ac).T + drive @ (mdl.Cy @ mdl.Bc).T) * mdl.out_gain
        return MeanResponse(t=(k0 + np.arange(n)) * mdl.Ts, x=x, drive=drive, gain=gain, drive_var=var,
                            distortion_var=dvar, ydot=ydot, y=y)

    def _drive_noise_var_from(self, k0: int, n: int) -> np.ndarray:
        """:meth:`drive_noise_var` at k = k0..k0+n-1 (n, m), for k0 past the first block: with
        Pa_inf = sum_{i>=0} F^i G G^T F^i^T (the Lyapunov solution; the actuator sources are
        stable, AR(1) with rho < 1), Pa_k = sum_{i<k} F^i G G^T F^i^T = Pa_inf - F^k Pa_inf F^k^T,
        so diag(C_a Pa_k C_a^T) = diag(C_a Pa_inf C_a^T) - diag(W_k Pa_inf W_k^T), W_k = C_a F^k.
        The difference's rounding, relative to Pa_k, is ~eps Pa_inf / Pa_k = eps / (1 - rho^(2k)),
        ~eps tau / (2k) for a correlation time of tau samples: below 1e-7 for k >= HORIZON_MAX and
        every tau a model file allows (at most 1e15 Ts)."""
        m = self.model.m
        DD = np.diag(sum((D @ D.T for D in self._Da), np.zeros((m, m))))
        GG = block_diag(*[G @ G.T for G in self._Ga]) if self._Ga else np.zeros((0, 0))
        F, Ca = self._Fa, self._Ca
        if F.shape[0] == 0 or not np.any(GG):
            return np.broadcast_to(DD, (n, m)).copy()
        Pinf = solve_discrete_lyapunov(F, GG)
        W = Ca @ np.linalg.matrix_power(F, k0)                    # (m, na)
        Wk = _powers_apply(F.T, W.T, n)                           # (n, na, m): (W F^j)^T
        return np.diag(Ca @ Pinf @ Ca.T) - np.einsum("kam,ab,kbm->km", Wk, Pinf, Wk) + DD
