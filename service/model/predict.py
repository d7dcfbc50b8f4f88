"""Predictions of the model: mean response, covariance, PSD, ACF and Allan variance, per effect.

The linear-Gaussian part is one augmented discrete system (seed sections 4 and 7: colored effects
augment the state). Symbols -> names:

=========  ==========  =================================================================
symbol     name        meaning
=========  ==========  =================================================================
s_k        state       [x (plant + lag), actuator-noise states, sensor-bias states]
F          ``F``       s_{k+1} = F s_k + Gamma e_k, e_k ~ N(0, I), columns owned by effects
Gamma      ``Gam``     noise input, (n_s, n_e)
H, J       ``H, J``    centered y_k = H s_k + J e_k + (white, walk, tone, jitter primitives)
P_k        ``P``       Cov(s_k), P_{k+1} = F P_k F^T + Gamma Gamma^T (seed section 4)
S_y,k      ``Sy``      Cov(y_k) = H P_k H^T + J J^T + R_v + R_q + R_b,k + ... (seed section 4)
R_b,k      walk        R_b,0 + k Q_b (seed sections 4 and 6.2)
=========  ==========  =================================================================

Effects contribute through the hooks of :mod:`.effects.base`. Independent sources add, so every
second-order prediction is a sum over the effects that own noise (``contributions``).

The predictor is built from one module per concept:

- :mod:`.mean_response`: the mean response to a command (seed section 3), the free response of a
  record that does not start at rest;
- :mod:`.linearize`: the statistical linearization of the static actuator nonlinearities (seed
  section 7);
- :mod:`.lyapunov`: the stationary covariance, a plant's integrator modes set apart;
- :mod:`.spectra`: PSD, ACF, variogram and Allan variance (their conventions are stated there);
- :mod:`.expected`: the expected value of each spectral estimator (E[Welch], E[segment ACF]).

Here: the augmented system (:meth:`Predictor.linear_system`), the covariance recursion, the steady
state, and the quantizer's correlated error.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import block_diag, solve_discrete_lyapunov

from ..memo import Memo
from .command import replayed
from .filter_cascade import output_filter_of, primitives, sensor_blocks

# _COLORS: the colored fits' memo, cleared (by the tests) with this module's memos below
from .linearize import _COLORS, Linearization, gain_switches  # noqa: F401
from .lyapunov import (
    _sensor_lyap,
    _settle_samples,
    leak_unit_modes,
    lyap_leaky,
    unit_projector,
    unit_tol,
)
from .mean_response import (
    HorizonAverages,
    MeanResponse,
    MeanResponses,
    free_response_fit,
    mean_key,
)
from .spectra import Spectra

# also importable from here, as before the prediction was split by concept (the diagnosis imports
# them from this module)
__all__ = ["HORIZON_MAX", "Covariance", "LinearSystem", "Predictor", "Steady",
           "free_response_fit", "gain_switches", "mean_key", "unit_tol"]


@dataclass
class LinearSystem:
    F: np.ndarray
    Gam: np.ndarray
    H: np.ndarray
    J: np.ndarray
    Hd: np.ndarray          # rows giving ydot (for jitter): ydot~ = Hd s + Jd e
    Jd: np.ndarray
    owners: dict            # effect id -> column indices of e
    n_x: int                # plant (+ lag) states at the top of s
    plant_block: slice      # rows/cols of s that are plant states (without lag)
    n_act: int = 0          # actuator-noise states after the plant's (shadows included)


@dataclass
class Covariance:
    P: np.ndarray                       # (N, n_s, n_s) state covariance P_k
    Sy: np.ndarray                      # (N, p) variance of y_k (diagonal of S_y,k)
    parts: dict = field(default_factory=dict)   # effect id -> (N, p) its share of Sy


@dataclass
class Steady:
    var_y: np.ndarray | None            # (p,) stationary variance of the centered measurement
    P: np.ndarray | None                # (n, n) plant state covariance, None if not stable
    contributions: dict                 # effect id -> (p,) or None
    bias_var_rate: np.ndarray           # (p,) growth of Var(y) per second from the bias walk
    stable: bool
    notes: list
    ydot_var: np.ndarray | None = None  # (p,) stationary Var(ydot) (the jitter's noise-driven slope)
    walk_var_rate: np.ndarray | None = None   # (p,) growth of Var(y) per second where the plant integrates


class _Columns:
    """The noise columns of the augmented system as they are added, each owned by an effect:
    Gamma's column block, and J's and Jd's (zero for a source that reaches y only through states)."""

    def __init__(self, n_s: int, p: int):
        self.n_s, self.p = n_s, p
        self.owners: dict = {}
        self.start = 0
        self.cols, self.Jc, self.Jdc = [], [], []

    def add(self, eid: str, col: np.ndarray, j: np.ndarray | None = None, jd: np.ndarray | None = None) -> None:
        k = col.shape[1]
        z = np.zeros((self.p, k))
        self.owners[eid] = np.concatenate([self.owners.get(eid, np.zeros(0, np.int64)),
                                           np.arange(self.start, self.start + k)])
        self.start += k
        self.cols.append(col)
        self.Jc.append(z if j is None else j)
        self.Jdc.append(z if jd is None else jd)

    def stacked(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(Gamma, J, Jd)."""
        Gam = np.hstack(self.cols) if self.cols else np.zeros((self.n_s, 0))
        J = np.hstack(self.Jc) if self.Jc else np.zeros((self.p, 0))
        Jd = np.hstack(self.Jdc) if self.Jdc else np.zeros((self.p, 0))
        return Gam, J, Jd


# The model's own mean response over its horizon, shared between models that differ only in what
# it does not depend on (:func:`mean_key`): a diagnosis builds thousands of models that differ in a
# noise parameter, and each one's steady state needs the mean when the model has a quantizer, a
# jitter or a nonlinearity, and the mean response is an O(N) simulation of the horizon while the
# steady state is O(n^3). Read-only arrays, shared by threads (a :class:`Memo`: they
# may compute one twice, never wrongly). Only means of at most _OWN_MEAN_BYTES are kept: the horizon
# is 60 s of samples (at most HORIZON_MAX), about 100 MB of mean response at Ts = 57 us and below.
_OWN_MEAN = Memo(9, flush=True)
_OWN_MEAN_BYTES = 16 << 20
# The horizon averages of a model whose horizon is longer than HORIZON_MAX (:meth:`Predictor._own_averages`),
# by the key of _OWN_MEAN and the horizon's length: small, but seconds to compute at Ts = 1 us.
_OWN_AVERAGES = Memo(9, flush=True)


HORIZON_MAX = 1 << 20
"""The most samples of the model's own mean response held at once (the 60 s horizon fits for
Ts >= 57 us): it keeps several arrays of that length. A longer horizon's averages of the mean
response (the jitter's slope, the quantizer's spread) are taken over all of it in blocks of this
length (:meth:`Predictor._own_averages`); the nonlinearities' linearization (rms gain, distortion
and their spectral fits, which must share one window) and the quantizer's motion take the first
HORIZON_MAX samples."""


class Predictor(MeanResponses, Linearization, Spectra):
    """Predictions for one model. ``horizon_s`` sets how long a command history is averaged over
    for signal-dependent approximations (jitter, nonlinear actuator gains), at most
    :data:`HORIZON_MAX` samples."""

    def __init__(self, model, horizon_s: float = 60.0):
        self.model = model
        self.span = max(int(np.ceil(horizon_s / model.Ts)), 2)     # the horizon, samples
        rec = replayed(model.command.params["replay"]) if "replay" in model.command.params else None
        if rec is not None:
            self.span = max(rec.shape[0], 2)         # a replayed record's command: the whole record
        self.horizon = min(self.span, HORIZON_MAX)                   # of it held at once
        m = model
        self._act_src = [e for e in m.effects.values() if hasattr(e, "drive_linear")]
        self._nonlin = [e for e in m.effects.values() if hasattr(e, "knots")]
        self._sen_lin = [e for e in m.effects.values() if hasattr(e, "sensor_linear")]
        self._filter = output_filter_of(m)
        self._sen_blocks = sensor_blocks(m, self._sen_lin, self._filter)
        blocks = [e.drive_linear() for e in self._act_src]
        self._act_blocks = blocks            # per source: (F, G, C, D)
        mm = m.m
        self._Fa = block_diag(*[b[0] for b in blocks]) if blocks else np.zeros((0, 0))
        self._Ga = [b[1] for b in blocks]
        self._Ca = np.hstack([b[2] for b in blocks]) if blocks else np.zeros((mm, 0))
        self._Da = [b[3] for b in blocks]
        if self._Fa.shape != (self._Ca.shape[1],) * 2:     # block_diag of 0x0 blocks
            self._Fa = np.zeros((self._Ca.shape[1],) * 2)
        self._steady_cache = None

    def _own_mean(self) -> MeanResponse:
        """:meth:`mean_response` of the model's own command over the horizon, shared through
        :data:`_OWN_MEAN` (read-only: not for callers that change it)."""
        key = (mean_key(self.model), self.horizon)
        got = _OWN_MEAN.get(key)
        if got is None:
            got = self.mean_response()
            arrays = [v for v in vars(got).values() if isinstance(v, np.ndarray)]
            for v in arrays:
                v.setflags(write=False)
            if sum(v.nbytes for v in arrays) <= _OWN_MEAN_BYTES:
                _OWN_MEAN.put(key, got)
        return got

    def _own_averages(self, mean: MeanResponse) -> HorizonAverages:
        """The averages (:class:`HorizonAverages`) of the model's own mean response over the whole
        horizon, ``mean`` being its first :attr:`horizon` samples (:meth:`_own_mean`).

        Each is (1 / (n - b)) sum_{k=b}^{n-1} f(m_k) of the mean response m_k (b: the burn). Within
        HORIZON_MAX that is taken on ``mean`` itself. Beyond, the horizon is gone through in blocks of
        HORIZON_MAX samples, each block's mean response started from the state the recursion
        m_{k+1} = A_d m_k + B_d E[drive_k] reaches at its start, so every block holds the very
        samples the whole horizon's recursion gives; the sums add over blocks (the variance by
        Chan's pairwise update of count, mean and squared deviations). So the average is the one
        over the full horizon, to rounding, in the memory of one block: taken over the first
        HORIZON_MAX samples alone, a slow command's average covered part of its period (a 0.03 Hz
        sine at Ts = 20 us: the first 21 s of its 33 s period, the jitter's variance 39 % high). The
        time is that of the horizon's samples, at most 6e7 (60 s at the model files' least Ts, 1 us:
        ~7 s for the seed's plant)."""
        mdl = self.model
        n, settle = self.span, _settle_samples(mdl)
        burn = min(n // 2, settle)
        if n == mean.t.size:
            return HorizonAverages(burn, np.mean(mean.ydot[burn:] ** 2, axis=0), np.var(mean.y[burn:], axis=0),
                                   float(mean.t[-1] - mean.t[burn]))

        def compute():
            ydot2 = np.zeros(mdl.p)
            count, y_mean, y_m2 = 0, np.zeros(mdl.p), np.zeros(mdl.p)
            block, k0 = mean, 0
            while True:
                a = max(burn - k0, 0)
                if a < block.t.size:
                    y = block.y[a:]
                    ydot2 += np.sum(block.ydot[a:] ** 2, axis=0)
                    nb, mb = y.shape[0], np.mean(y, axis=0)
                    m2b = np.sum((y - mb) ** 2, axis=0)
                    delta, total = mb - y_mean, count + nb
                    y_m2 = y_m2 + m2b + delta**2 * count * nb / total
                    y_mean = y_mean + delta * nb / total
                    count = total
                k_next = k0 + block.t.size
                if k_next >= n:
                    break
                x_next = mdl.Ad @ block.x[-1] + mdl.Bd @ block.drive[-1] if mdl.n_x else np.zeros(0)
                block = self._mean_block(k_next, min(HORIZON_MAX, n - k_next), x_next)
                k0 = k_next
            return HorizonAverages(burn, ydot2 / count, y_m2 / count, float((n - 1) * mdl.Ts - burn * mdl.Ts))
        return _OWN_AVERAGES.get_or_compute((mean_key(mdl), n), compute)

    # -- the augmented linear system -------------------------------------------------------------------
    def linear_system(self, g: np.ndarray | None = None, dstd: np.ndarray | None = None,
                      shadow: dict | None = None, dcolor: list | None = None) -> LinearSystem:
        """The augmented system for nonlinearity gain ``g`` and distortion std ``dstd`` (per input).
        The distortion d of the static nonlinearities enters the input channel as white noise of
        std ``dstd``, owned by the nonlinearity (exact for white actuator noise, whose distortion
        is iid); of a colored noise, the colored part is ``dcolor``.

        ``shadow`` ({index of an actuator source: (mean gain (m,), [shadow block (F, G, C, D)])},
        :meth:`_gain_shadows`): a colored source whose gain switches within its correlation time,
        g_k n_k = gbar n_k + (g_k - gbar) n_k. The first part keeps the source's own dynamics at
        the mean gain, the second (uncorrelated with it over time) is the shadow blocks (their
        variance in their G), all owned by the source.

        ``dcolor`` ([block (F, G, C, D)], :meth:`_distortion_colors`): the colored part of the
        distortion of a colored source, owned by the nonlinearity beside its white part ``dstd``.

        State order: plant (+ lag), the actuator blocks, the sensor-bias states; noise columns:
        the actuator blocks', the distortion's, the state-noise sources', the sensor states'."""
        mdl = self.model
        act, act_ids = self._actuator_blocks(g, shadow or {}, dcolor)
        blocks = [b for bl in act for b in bl]
        sen = [blk for _, blk in self._sen_blocks]
        F, na = self._transition(blocks, sen)
        n_s, nx = F.shape[0], mdl.n_x
        cols = _Columns(n_s, mdl.p)
        gain = mdl.out_gain[:, None]
        CyBc = mdl.Cy @ mdl.Bc
        a0 = 0
        for eid, bl in zip(act_ids, act):
            for _, Ga, _, Da, Gi in bl:
                k, ka = Da.shape[1], Ga.shape[0]
                col = np.zeros((n_s, k))
                col[:nx] = mdl.Bd @ Gi @ Da
                col[nx + a0:nx + a0 + ka] = Ga
                a0 += ka
                cols.add(eid, col, gain * (mdl.Dy @ Gi @ Da), gain * (CyBc @ Gi @ Da))
        if self._nonlin and dstd is not None:
            Dd = np.diag(np.asarray(dstd, float))
            col = np.zeros((n_s, mdl.m))
            col[:nx] = mdl.Bd @ Dd
            cols.add(self._distortion_owner(), col, gain * (mdl.Dy @ Dd), gain * (CyBc @ Dd))
        for eid, sl in mdl.proc_columns.items():              # x_{k+1} += S e_k per state-noise source
            if sl.stop > sl.start:
                col = np.zeros((n_s, sl.stop - sl.start))
                col[:nx] = mdl.S_proc[:, sl]
                cols.add(eid, col)
        s0 = 0
        for eid, (Fi, Gi, Hi, Ji) in self._sen_blocks:
            col = np.zeros((n_s, Gi.shape[1]))
            col[nx + na + s0:nx + na + s0 + Gi.shape[0]] = Gi
            s0 += Gi.shape[0]
            cols.add(eid, col, Ji)
        H, Hd = self._output_rows(blocks, sen, n_s, na)
        Gam, J, Jd = cols.stacked()
        return LinearSystem(F, Gam, H, J, Hd, Jd, cols.owners, nx, slice(0, mdl.plant.n), na)

    def _actuator_blocks(self, g, shadow: dict, dcolor) -> tuple[list, list]:
        """Per actuator source (and the distortion's colored part): its blocks (F, G, C, D, gain
        matrix), its own states then its shadow's; and the owner of each."""
        mdl = self.model
        G = np.diag(np.ones(mdl.m) if g is None else np.asarray(g, float))
        act = []
        for i, (Fi, Ga, Ci, Da) in enumerate(self._act_blocks):
            if i in shadow:
                gbar, comps = shadow[i]
                act.append([(Fi, Ga, Ci, Da, np.diag(gbar))] + [(*blk, np.eye(mdl.m)) for blk in comps])
            else:
                act.append([(Fi, Ga, Ci, Da, G)])
        act_ids = [e.id for e in self._act_src]
        if self._nonlin and dcolor:
            act.append([(*blk, np.eye(mdl.m)) for blk in dcolor])
            act_ids.append(self._distortion_owner())
        return act, act_ids

    def _transition(self, blocks: list, sen: list) -> tuple[np.ndarray, int]:
        """F of s = [plant (+ lag), actuator blocks' states, sensor states], and the actuator
        states' count: the plant driven by each block's output through B_d times its gain."""
        mdl = self.model
        na = sum(b[0].shape[0] for b in blocks)
        Fs = block_diag(*[s[0] for s in sen]) if sen else np.zeros((0, 0))
        nx = mdl.n_x
        n_s = nx + na + Fs.shape[0]
        F = np.zeros((n_s, n_s))
        F[:nx, :nx] = mdl.Ad
        a0 = 0
        for Fi, _, Ci, _, Gi in blocks:
            k = Fi.shape[0]
            F[:nx, nx + a0:nx + a0 + k] = mdl.Bd @ Gi @ Ci
            F[nx + a0:nx + a0 + k, nx + a0:nx + a0 + k] = Fi
            a0 += k
        F[nx + na:, nx + na:] = Fs
        return F, na

    def _output_rows(self, blocks: list, sen: list, n_s: int, na: int) -> tuple[np.ndarray, np.ndarray]:
        """H (y from s) and Hd (ydot from s, for the jitter), times the sensor gain."""
        mdl = self.model
        nx = mdl.n_x
        gain = mdl.out_gain[:, None]
        CyBc = mdl.Cy @ mdl.Bc
        H = np.zeros((mdl.p, n_s))
        H[:, :nx] = gain * mdl.Cy
        H[:, nx + na:] = np.hstack([s[2] for s in sen]) if sen else np.zeros((mdl.p, 0))
        Hd = np.zeros((mdl.p, n_s))
        Hd[:, :nx] = gain * (mdl.Cy @ mdl.Ac)
        a0 = 0
        for Fi, _, Ci, _, Gi in blocks:
            k = Fi.shape[0]
            H[:, nx + a0:nx + a0 + k] = gain * (mdl.Dy @ Gi @ Ci)
            Hd[:, nx + a0:nx + a0 + k] = gain * (CyBc @ Gi @ Ci)
            a0 += k
        return H, Hd

    # -- primitives (non-state effects) ----------------------------------------------------------------
    def _primitives(self, mean: MeanResponse | None = None, jitter_ydot2: np.ndarray | None = None):
        """[(effect id, kind, params)] for white / walk / tone / jitter contributions, through the
        sensor's own filter where they pass it (:func:`.filter_cascade.primitives`)."""
        return primitives(self.model, self._filter)

    def stationary_starts(self, ls=None) -> list:
        """[(effect id, state indices, covariance at k = 0)] of the sensor sources that start
        stationary (``initial_cov``), in the augmented system ``ls`` (default: the steady state's).
        A source's own states lead its block; a filter's after them start at rest."""
        if ls is None:
            self.steady_state()
            ls = self._ls
        out = []
        s0 = ls.n_x + ls.n_act
        for eid, (Fi, *_) in self._sen_blocks:
            e = self.model.effects[eid]
            if hasattr(e, "initial_cov"):
                k = e.sensor_linear()[0].shape[0]
                out.append((eid, np.arange(s0, s0 + k), e.initial_cov()))
            s0 += Fi.shape[0]
        return out

    # -- covariance recursion (seed section 4) -----------------------------------------------------------
    def covariance(self, n: int, command: np.ndarray | None = None) -> Covariance:
        """P_k and S_y,k for k = 0..n-1 from P_0 = 0 (the noise states start at zero, as in the
        simulation, but a sensor source's that start in its steady state: its ``initial_cov()``);
        S_y,k includes R_b,k = R_b,0 + k Q_b, the white primitives and the jitter's signal-dependent
        variance std_s^2 E[ydot_k^2]."""
        mean = self.mean_response(n, command)
        n = mean.t.size
        parts: dict = {}
        const = not self._nonlin
        dstd = np.sqrt(mean.distortion_var)
        ls = self.linear_system(None if const else mean.gain[0], None if const else dstd[0])
        n_s = ls.F.shape[0]
        Pj = {eid: np.zeros((n_s, n_s)) for eid in ls.owners}
        for eid, idx, cov in self.stationary_starts(ls):
            Pj[eid][np.ix_(idx, idx)] = cov
        P_hist = np.zeros((n, n_s, n_s))
        Sy = {eid: np.zeros((n, self.model.p)) for eid in ls.owners}
        ydot_var = np.zeros((n, self.model.p))
        for k in range(n):
            if not const:
                ls = self.linear_system(mean.gain[k], dstd[k])
            Ptot = np.zeros((n_s, n_s))
            for eid, cols in ls.owners.items():
                Pk = Pj[eid]
                Ptot += Pk
                Jj = ls.J[:, cols]
                Sy[eid][k] = np.einsum("ij,jk,ik->i", ls.H, Pk, ls.H) + np.sum(Jj**2, axis=1)
                Jdj = ls.Jd[:, cols]
                ydot_var[k] += np.einsum("ij,jk,ik->i", ls.Hd, Pk, ls.Hd) + np.sum(Jdj**2, axis=1)
                Gj = ls.Gam[:, cols]
                # P_{k+1} = F P_k F^T + Gamma Gamma^T   (per source; seed section 4)
                Pj[eid] = ls.F @ Pk @ ls.F.T + Gj @ Gj.T
            P_hist[k] = Ptot
        parts.update(Sy)
        k_idx = np.arange(n)
        for eid, kind, *prm in self._primitives():
            if kind == "white":
                parts[eid] = np.broadcast_to(prm[0], (n, self.model.p)).copy()
            elif kind == "walk":
                q, var0, flt = prm
                if flt is None:
                    parts[eid] = var0 + k_idx[:, None] * q       # R_b,k = R_b,0 + k Q_b
                else:
                    # through the filter from rest: var0 s_k^2 + q sum_(m<k) s_m^2 (:mod:`.effects.sensor_filter`)
                    s2 = flt.step_response(n) ** 2
                    parts[eid] = var0 * s2 + q * np.concatenate([np.zeros((1, self.model.p)), np.cumsum(s2, axis=0)[:-1]])
            elif kind == "tone":            # an effect of several lines: their variances add
                parts[eid] = parts.get(eid, 0.0) + np.broadcast_to(prm[0] ** 2 / 2.0, (n, self.model.p))
            elif kind == "jitter":
                parts[eid] = prm[0] * (mean.ydot**2 + ydot_var)
        total = sum(parts.values(), np.zeros((n, self.model.p)))
        return Covariance(P=P_hist, Sy=total, parts=parts)

    # -- steady state ------------------------------------------------------------------------------
    def steady_state(self) -> Steady:
        """Stationary covariance by the discrete Lyapunov equation P = F P F^T + Gamma Gamma^T,
        per source. Signal-dependent terms (jitter, nonlinear gains) are averaged over the
        horizon of the model's own command. The bias walk is reported as a rate, not a variance."""
        if self._steady_cache is not None:
            return self._steady_cache
        # unstable in continuous time, or only as discretized (forward Euler over a Ts beyond
        # 2 / |eigenvalue|: a stiff spring at the seed's 10 ms)
        unstable = (np.any(np.linalg.eigvals(self.model.Ac).real > 0)
                    or np.any(np.abs(np.linalg.eigvals(self.model.Ad)) > 1))
        if unstable:
            # an unstable plant's mean response overflows on the way: its contributions come out
            # None and the callers say the plant is unstable; the overflow warnings are no news
            with np.errstate(over="ignore", invalid="ignore"):
                return self._steady_state()
        return self._steady_state()

    def _steady_state(self) -> Steady:
        mdl = self.model
        notes = []
        # the mean response over the horizon only where a term depends on the signal (the
        # nonlinearities' gains, the effects' ``signal_dependent`` terms: the jitter's slope, the
        # quantizer's spread): at Ts <= 57 us the horizon is 10^6 samples, seconds and 100s of MB
        # for a model that needs none of it
        needs_mean = bool(self._nonlin) or any(e.signal_dependent for e in mdl.effects.values())
        mean = self._own_mean() if needs_mean else None
        avg = self._own_averages(mean) if needs_mean else None
        ls = self._linearized_system(mean, notes) if self._nonlin else self.linear_system(None, None, {}, [])
        plant_part = slice(0, ls.n_x + ls.n_act)
        marginal, walk_y, walk_ydot = self._integrator_modes(ls, notes)
        rad = np.max(np.abs(np.linalg.eigvals(ls.F[plant_part, plant_part])), initial=0.0)
        stable = bool(rad < 1.0) and not marginal
        marginal = marginal and bool(rad < 1.0)
        contributions, Pj, Dj, Ptot, ydot_var = self._source_covariances(ls, stable, marginal, walk_y)
        walk_rate = None
        if marginal:
            # the walk's part of y takes H Pi Gamma w_k per sample (Pi: :func:`unit_projector`)
            HPi = ls.H @ unit_projector(ls.F)
            walk_rate = sum((np.sum((HPi @ ls.Gam[:, c]) ** 2, axis=1) for c in ls.owners.values()),
                            np.zeros(mdl.p)) / mdl.Ts
        slope_ok = stable or (marginal and not walk_ydot.any())
        ydot2 = avg.ydot2 if needs_mean else np.zeros(mdl.p)
        rate = self._primitive_contributions(contributions, ydot2, ydot_var, slope_ok)
        if needs_mean:
            # from the measurement back up the chain (what reaches an effect after the sum first)
            for e in reversed(list(mdl.effects.values())):
                others = sum(v for k, v in contributions.items() if v is not None and k != e.id)
                note = e.approximation_note(avg, others)
                if note:
                    notes.append(note)
        var_y = None if any(v is None for v in contributions.values()) else \
            sum(contributions.values(), np.zeros(mdl.p))
        Pp = Ptot[ls.plant_block, ls.plant_block] if stable else None
        # published whole, the cache last: a predictor shared by threads (the comparison's views) may
        # compute its steady state in two at once, and each reads complete, equal dicts
        self._Pj, self._Dj, self._ls = Pj, Dj, ls
        self._steady_cache = Steady(var_y=var_y, P=Pp, contributions=contributions,
                                    bias_var_rate=rate, stable=stable, notes=notes,
                                    ydot_var=ydot_var if slope_ok else None, walk_var_rate=walk_rate)
        return self._steady_cache

    def _linearized_system(self, mean: MeanResponse, notes: list) -> LinearSystem:
        """The augmented system with the actuator nonlinearities linearized around the model's own
        mean drive (seed section 7), its notes appended to ``notes``: the gains after the transient
        (the drive noise's variance grows from zero at the start), over the samples held, the
        window of their spectral fits (:meth:`_colors`) too."""
        mdl = self.model
        burn = min(mean.t.size // 2, _settle_samples(mdl))
        g = np.sqrt(np.mean(mean.gain[burn:] ** 2, axis=0))
        dstd = np.sqrt(np.mean(mean.distortion_var[burn:], axis=0))
        shadow, dcolor = self._colors(mean, burn, dstd)
        notes.append("actuator nonlinearities linearized around the mean drive (seed section 7): "
                     "rms gain " + ", ".join(f"{v:.4g}" for v in g) + ", distortion std "
                     + ", ".join(f"{v:.3g}" for v in dstd)
                     + (" treated as white" if not dcolor else "")
                     + (f", over the first {mean.t.size * mdl.Ts:.4g} s of the command (the samples held at "
                        f"once, HORIZON_MAX) of the {self.span * mdl.Ts:.4g} s horizon"
                        if self.span > mean.t.size else ""))
        for ch, (wvar, comps) in dcolor.items():
            notes.append(f"the distortion of input {ch}'s colored noise is colored too (Hermite terms of the "
                         f"noise's correlation): white std {np.sqrt(wvar):.3g} and {len(comps)} damped cosines")
            dstd[ch] = np.sqrt(wvar)
        for i, (gbar, comps) in shadow.items():
            gf = np.sqrt(np.maximum(g**2 - gbar**2, 0.0))
            notes.append(f"{self._act_src[i].id}: the nonlinearities' gain switches within its correlation "
                         "time: its mean gain " + ", ".join(f"{v:.4g}" for v in gbar) + " on its own "
                         "spectrum, the gain's fluctuation (std " + ", ".join(f"{v:.3g}" for v in gf)
                         + f") on {len(comps)} wider ones (damped cosines fitted to its spectrum)")
        return self.linear_system(g, dstd, shadow, [b for _, bl in dcolor.values() for b in bl])

    def _integrator_modes(self, ls: LinearSystem, notes: list) -> tuple[bool, np.ndarray, np.ndarray]:
        """(marginal, walk_y, walk_ydot): whether the plant integrates (A with an eigenvalue 0), and
        per output whether its walk reaches y (its slope). Such a plant's unit modes are made to
        leak in ``ls.F`` (:func:`leak_unit_modes`), its notes appended to ``notes``."""
        mdl = self.model
        nx = ls.n_x
        walk_y = walk_ydot = np.zeros(mdl.p, bool)
        leaked = leak_unit_modes(ls.F[:nx, :nx], mdl.Ac, mdl.Ts)
        if leaked is None:
            return False, walk_y, walk_ydot
        # the plant's unit modes leak by LEAK per sample, so that every source has a (huge)
        # stationary covariance whose increments are those of the exact walk. Only the plant's own
        # modes: a noise state's near-unit pole is its own model.
        ls.F[:nx, :nx], Vu = leaked
        # the outputs (and slopes) the walk reaches have no steady-state variance; the others
        # (a motor's speed beside its angle) keep theirs (Vu's columns are orthonormal Schur
        # vectors: unit length)
        walk_y = np.any(np.abs(ls.H[:, :nx] @ Vu) > 1e-9 * np.linalg.norm(ls.H), axis=1)
        walk_ydot = np.any(np.abs(ls.Hd[:, :nx] @ Vu) > 1e-9 * np.linalg.norm(ls.Hd), axis=1)
        if not walk_y.any():
            notes.append("the plant integrates (an eigenvalue of A at 0), but no output sees its walk: "
                         "the outputs keep their steady state")
        else:
            reached = "its output has" if mdl.p == 1 else \
                "output " + ", ".join(str(j) for j in np.flatnonzero(walk_y)) + f" (of 0..{mdl.p - 1}) has"
            notes.append(f"the plant integrates (an eigenvalue of A at 0): {reached} no steady-state "
                         "variance, only stationary increments (variogram, PSD of the differenced output)")
        return True, walk_y, walk_ydot

    def _source_covariances(self, ls: LinearSystem, stable: bool, marginal: bool, walk_y: np.ndarray):
        """Per noise source of the augmented system, its stationary covariance P_j (Lyapunov) and
        its share of Var(y): (contributions, P_j, D_j (marginal plants: (I - F) P_j), sum of P_j,
        Var(ydot) of the noise). A source that drives an unstable plant contributes None."""
        mdl = self.model
        n_s = ls.F.shape[0]
        plant_part = slice(0, ls.n_x + ls.n_act)
        contributions: dict = {}
        Ptot = np.zeros((n_s, n_s))
        ydot_var = np.zeros(mdl.p)
        Pj: dict = {}
        Dj: dict = {}           # marginal plants: (I - F) P per source, formed without cancellation
        for eid, cols in ls.owners.items():
            Gj = ls.Gam[:, cols]
            drives_plant = bool(np.any(Gj[plant_part] != 0))
            if drives_plant and not (stable or marginal):
                contributions[eid] = None
                continue
            if marginal:
                Pk, Dj[eid] = lyap_leaky(ls.F, Gj @ Gj.T)
            else:
                Pk = solve_discrete_lyapunov(ls.F, Gj @ Gj.T) if stable else _sensor_lyap(ls, Gj, plant_part)
            Pk = 0.5 * (Pk + Pk.T)
            Pj[eid] = Pk
            Ptot += Pk
            Jj = ls.J[:, cols]
            c = np.einsum("ij,jk,ik->i", ls.H, Pk, ls.H) + np.sum(Jj**2, axis=1)
            if drives_plant and walk_y.any():
                # NaN where the walk reaches: no steady-state variance there (null in the JSON)
                c = None if walk_y.all() else np.where(walk_y, np.nan, c)
            contributions[eid] = c
            ydot_var += np.einsum("ij,jk,ik->i", ls.Hd, Pk, ls.Hd) + np.sum(ls.Jd[:, cols] ** 2, axis=1)
        return contributions, Pj, Dj, Ptot, ydot_var

    def _primitive_contributions(self, contributions: dict, ydot2: np.ndarray, ydot_var: np.ndarray,
                                 slope_ok: bool) -> np.ndarray:
        """The primitives' (:meth:`_primitives`) shares of Var(y) put into ``contributions``; returns
        the walks' growth of Var(y) per second. A slope-modulated white noise's (``jitter``) is
        s2 (E[ydot]^2 + Var(ydot)), None where the noise's slope has no steady state."""
        mdl = self.model
        rate = np.zeros(mdl.p)
        for eid, kind, *prm in self._primitives():
            if kind == "white":
                contributions[eid] = np.broadcast_to(prm[0], (mdl.p,)).copy()
            elif kind == "walk":
                rate = rate + prm[0] / mdl.Ts
            elif kind == "tone":            # an effect of several lines: their variances add
                contributions[eid] = contributions.get(eid, 0.0) + prm[0] ** 2 / 2.0
            elif kind == "jitter":
                contributions[eid] = prm[0] * (ydot2 + ydot_var) if slope_ok or not ydot_var.any() else None
        return rate

    # -- the quantizer's correlated error (:mod:`.effects.sensor_quantization`) ----------------------------
    def motion(self, n: int, mean_y: np.ndarray | None = None, k0: int = 0) -> np.ndarray:
        """The deterministic part of the signal before the quantizer over n samples: the mean
        response (``mean_y`` from sample ``k0``, default the model's own command after its
        transient) plus the tones (phase 0: only their increments matter, over many periods)."""
        mdl = self.model
        if mean_y is None:
            k0 = _settle_samples(mdl)
            mean_y = self.mean_response(k0 + n).y[k0:]
        mean_y = np.asarray(mean_y, float)
        t = (k0 + np.arange(mean_y.shape[0])) * mdl.Ts
        out = mean_y.copy()
        for eid, kind, *prm in self._primitives():
            if kind == "tone":
                out = out + np.asarray(prm[0], float) * np.sin(2 * np.pi * t[:, None] * np.asarray(prm[1], float))
        return out

    def tone_ids(self) -> set:
        """Ids of the effects that are spectral lines (deterministic in a record: random phase only)."""
        return {eid for eid, kind, *_ in self._primitives() if kind == "tone"}

    def after_sum(self):
        """The effect that acts on the measurement after every other term is summed
        (``acts_after_sum``: a quantizer), the last in the chain; None without one."""
        return next((e for e in reversed(list(self.model.effects.values())) if e.acts_after_sum), None)

    def before_quantizer(self, gam: dict) -> np.ndarray:
        """The variogram (L, p) of the random part of the signal before the effect acting after the
        sum (:meth:`after_sum`): the sum of the effects' variograms ``gam`` ({id: (L, p)}) but its
        own and the tones' (the tones are deterministic: in :meth:`motion`)."""
        q = self.after_sum()
        skip = self.tone_ids() | ({q.id} if q is not None else set())
        L = next(iter(gam.values())).shape[0]
        return sum((v for eid, v in gam.items() if eid not in skip and v is not None),
                   np.zeros((L, self.model.p)))

    def quantization_acf(self, gam: dict, motion: np.ndarray | None, cache: Memo | None = None,
                         moments=None, stein: bool = True) -> np.ndarray:
        """R_e(d) of the quantizer's error (L, p) from the other effects' variograms ``gam`` ({id:
        (L, p)}, :meth:`before_quantizer`) and the deterministic ``motion``. ``moments``
        (:meth:`quantizer_moments`): the error's conditional mean is in the mean response; the part
        is then the covariance about it, the error's covariance with the noise included unless
        ``stein`` is False (the likelihood scales the noise's own parts instead)."""
        q = self.after_sum()
        cross = None
        if moments is not None and stein:
            # c(d) of the stationary random part: a walk's covariance with the error (2 h times its
            # growing variance) is left out, and so are the tones (deterministic here, in the motion)
            walks = self.walk_ids()
            st = self.steady_state()
            stat = {eid: v for eid, v in gam.items() if eid not in walks}
            keep = set(stat) - {q.id} - self.tone_ids()
            # (a source through a plant that integrates is left out where its walk reaches: NaN)
            sig2 = sum((np.nan_to_num(np.asarray(st.contributions[e], float)) for e in keep
                        if st.contributions.get(e) is not None), np.zeros(self.model.p))
            cross = sig2 - self.before_quantizer(stat)
        return q.error_acf(self.before_quantizer(gam), motion, cache, moments, cross)

    def quantizer_moments(self, mu: np.ndarray, k0: int = 0):
        """The quantizer's conditional moments (:func:`.effects.sensor_quantization.conditional_moments`)
        over a record whose mean before the quantizer is ``mu`` (n, p) from sample ``k0``: the
        random part's variance is the stationary one of every other effect plus a bias walk's
        growth from its start. A tone counts as noise of variance A^2 / 2 here (its phase is not
        in the mean response: a large one spreads the signal over the steps and the mean goes),
        while the covariance (:meth:`quantization_acf`) follows it in the motion: an approximation
        for a tone beside a coarse quantizer. A jitter counts at the model's own command's level.
        None without a quantizer or a stationary prediction, or when no output's error depends
        on mu."""
        q = self.after_sum()
        if q is None:
            return None
        st = self.steady_state()
        if any(v is None or np.any(np.isnan(v)) for v in st.contributions.values()):
            return None
        mu = np.asarray(mu, float).reshape(len(mu), -1)
        sig2 = sum((np.asarray(v, float) for e, v in st.contributions.items() if e != q.id), np.zeros(self.model.p))
        walk0 = self.walk_initial_var()
        # the smallest variance (the record's start) decides whether any sample's mean is there
        if not np.any(q.moments_matter(sig2 + walk0)):
            return None
        if np.any(st.bias_var_rate > 0) or np.any(walk0 > 0):
            t = (k0 + np.arange(mu.shape[0]))[:, None] * self.model.Ts
            sig2 = sig2 + walk0 + st.bias_var_rate * t
        mo = q.error_moments(mu, sig2)
        return mo if mo is not None and mo.active.any() else None

    def walk_initial_var(self) -> np.ndarray:
        """(p,) Var(b_0) summed over the walks (their ``("walk", q, var0)`` primitives)."""
        return sum((np.asarray(prm[1], float) for _, kind, *prm in self._primitives() if kind == "walk"),
                   np.zeros(self.model.p))

    def slope_modulated(self) -> dict:
        """{effect id: s2} of the white noises whose variance follows the signal's slope,
        s2 ydot_k^2 (their ``("jitter", s2)`` primitives)."""
        return {eid: prm[0] for eid, kind, *prm in self._primitives() if kind == "jitter"}

    def walk_ids(self) -> set:
        """Ids of the effects that are walks (nonstationary: a growing variance, no ACF)."""
        return {eid for eid, kind, *_ in self._primitives() if kind == "walk"}

