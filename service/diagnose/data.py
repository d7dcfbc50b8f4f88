"""The record the diagnosis works on and its residual against a model's mean response.

:class:`Data`: the samples, the recorded command, the periodogram of the differenced record and
what the data alone say (the command's lines, a quantization grid). :func:`mean_response`: the
model's predicted response to the recorded command, whose difference from y is the residual.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np
import scipy.fft as sfft

from ..memo import Memo
from ..model.simulate import lsim
from . import whittle as W
from .thresholds import COMB_LINES, GRID_TOL, LINE_SHARE, REL_BW


# -- the data ---------------------------------------------------------------------------------------------
@dataclass
class Data:
    """What the diagnosis works on: y (N, p), the recorded command u (N, m) or None, and whether the
    record starts at rest (sample 0 of a noiselab stream). ``k0``: first sample analysed (0 at
    rest; else after the nominal model's transient)."""

    y: np.ndarray
    u: np.ndarray | None
    Ts: float
    at_rest: bool
    k0: int = 0
    notes: list = field(default_factory=list)
    ramps: object = None          # the taper ramps' term (:class:`.whittle.Ramps`), set by the first Hypotheses
    feedback: object = None       # the command against the residual's past (:class:`.closed_loop.Feedback`)
    fed_back: np.ndarray = field(default_factory=lambda: np.zeros(0))   # command lines copied from y
    stable: bool = False          # the plant is stable (a stationary level: ``Evaluator.level_term``), set there too

    def __post_init__(self):
        self.y = np.asarray(self.y, float).reshape(len(self.y), -1)
        # the transforms are O(M log M) only for smooth M: drop up to ~0.1 % of the samples at the end
        n_all = self.y.shape[0]
        M = smooth_len(n_all - self.k0 - 1)
        if self.k0 + 1 + M < n_all:
            self.notes.append(f"the last {n_all - self.k0 - 1 - M} samples are left out of the spectral fit "
                              f"(a transform length of {M} samples is fast)")
            self.y = self.y[:self.k0 + 1 + M]
            if self.u is not None:
                self.u = np.asarray(self.u, float)[:self.k0 + 1 + M]
        self.N, self.p = self.y.shape
        self.M = self.N - self.k0 - 1
        self.nf = W.n_freqs(self.M)
        self.n_bic = self.N * self.p
        self.t = np.arange(self.N) * self.Ts
        # a command that varies, or (a record from rest) one that is not zero: a constant command
        # from sample 0 is a step at t = 0 for a plant at rest (the default step, time_s = 0)
        self.has_command = self.u is not None and self.u.size > 0 and bool(
            np.any(np.ptp(self.u, axis=0) > 0) or (self.at_rest and np.any(self.u != 0)))
        # not from rest under a command: the mean state at k0 is fitted (:meth:`.evaluator.Evaluator.mean`)
        self.free_start = not self.at_rest and self.u is not None and bool(np.any(self.u != 0))
        self.umax = float(np.max(np.abs(self.u))) if self.u is not None and self.u.size else 0.0
        # per input (a limit searched per input ranges over its own command's)
        self.umax_in = np.max(np.abs(self.u), axis=0) if self.u is not None and self.u.size else np.zeros(0)
        self.T = self.N * self.Ts
        self.groups = W.Groups(self.M, REL_BW)
        self.starts, self.sizes = self.groups.starts, self.groups.sizes
        # Whittle weights: bins per group; the DC bin (group 0, alone) is real: chi-squared 1, half weight
        self.weights = self.sizes.copy()
        self.weights[0] = 0.5
        self.grid = quantization_grid(self.y)
        self._lines = None

    def command_lines(self) -> np.ndarray:
        """Frequencies (Hz) of the recorded command's spectral lines (a sine, a square wave's
        harmonics): bins 100x above the median of their 20 neighbours and above 1e-8 of the
        largest, local maxima, that carry at least :data:`.thresholds.LINE_SHARE` of the command's power (with
        their two neighbours: an off-bin line leaks into them); none when more than
        :data:`.thresholds.COMB_LINES` do. A periodic broadband command (a chirp repeated every
        ``duration_s``, a maximal-length PRBS) is a comb of hundreds to thousands of weak lines up
        to the Nyquist frequency: their harmonics' zones would cover every frequency, so that no
        interference tone could be found (a square wave keeps its first odd harmonics). Empty
        without a command. Set once computed whole (a thread that asks meanwhile computes them
        too, never reads an unfinished value)."""
        if self._lines is None:
            lines = np.zeros(0)
            if self.has_command:
                from scipy.ndimage import median_filter
                x = self.u[self.k0:] - np.mean(self.u[self.k0:], axis=0)
                P = np.sum(np.abs(sfft.rfft(np.ascontiguousarray(x.T), axis=-1)) ** 2, axis=0)
                P[0] = 0.0
                med = median_filter(P, size=21, mode="nearest")
                peak = np.zeros(P.size, bool)
                peak[1:-1] = (P[1:-1] >= P[:-2]) & (P[1:-1] >= P[2:])
                idx = np.flatnonzero(peak & (P > 100 * med) & (P > 1e-8 * P.max()))
                share = (P[idx] + P[idx - 1] + P[np.minimum(idx + 1, P.size - 1)]) / max(float(P.sum()), 1e-300)
                idx = idx[share >= LINE_SHARE]
                if idx.size <= COMB_LINES:
                    lines = idx / (x.shape[0] * self.Ts)
            self._lines = lines
        return self._lines

    def reference_lines(self) -> np.ndarray:
        """The command's lines that are the reference's: :meth:`command_lines` but those a controller
        copied from the measurement into the command (``fed_back``, :mod:`.closed_loop`): those are
        the measurement's lines, not the mean response's."""
        lines = self.command_lines()
        if not self.fed_back.size:
            return lines
        return np.array([f for f in lines if not np.any(np.isclose(f, self.fed_back, rtol=0, atol=1e-9))])

    def group(self, A: np.ndarray) -> np.ndarray:
        """Means over the frequency groups (nb, ...)."""
        return self.groups.mean(A)


def smooth_len(n: int) -> int:
    """The largest m <= n whose prime factors are 2, 3, 5 and 7."""
    m = n
    while m > 1:
        k = m
        for q in (2, 3, 5, 7):
            while k % q == 0:
                k //= q
        if k == 1:
            return m
        m -= 1
    return max(n, 1)


def quantization_grid(y: np.ndarray) -> list:
    """Per output: the step of the grid every value lies on (to GRID_TOL), or None."""
    out = []
    for j in range(y.shape[1]):
        v = np.unique(y[:, j])
        step = None
        if v.size >= 3:
            d = np.diff(v)
            d0 = float(d.min())
            big = float(np.max(np.abs(v)))
            if d0 > 1e-9 * max(big, 1e-300):
                small = d[d < 1.5 * d0]
                s = float(np.median(small))
                k = v / s
                if np.max(np.abs(k - np.rint(k))) < GRID_TOL:
                    step = float(f"{s:.10g}")
        out.append(step)
    return out


# -- mean response and residual ----------------------------------------------------------------------------
def mean_response(model, data: Data, gain: bool = True):
    """E[y_k] and E[ydot_k] (N, p) for the recorded command (seed section 3, fast modal form);
    ``gain=False``: before the sensor gain."""
    pr = model.predictor()
    N = data.N
    u = np.asarray(data.u if data.u is not None else model.command.values(0, N, model.Ts), float)
    drive = mean_drive(pr, u)
    C = np.vstack([model.Cy, model.Cy @ model.Ac])
    D = np.vstack([model.Dy, model.Cy @ model.Bc])
    yy = lsim(model.Ad, model.Bd, C, D, drive)
    if not gain:
        return yy[:, :model.p], yy[:, model.p:]
    g = model.out_gain
    return yy[:, :model.p] * g, yy[:, model.p:] * g


def mean_drive(pr, u: np.ndarray) -> np.ndarray:
    """E[N(u_c,k + n_k)] (seed section 7), as :meth:`Predictor.drive_stats` but fast on long
    records: once the actuator noise variance has settled, the expectation is a fixed smooth
    function of u_c, tabulated on a fine grid (with the nonlinearities' kinks as grid points) and
    interpolated; without actuator noise it is N(u_c) itself."""
    if not pr._nonlin:
        return u.copy()
    N, m = u.shape
    var = pr.drive_noise_var(N)
    settled = np.flatnonzero(np.any(np.abs(var - var[-1]) > 1e-9 * np.abs(var[-1]), axis=1))
    k1 = int(settled[-1]) + 1 if settled.size else 0
    out = np.empty_like(u)
    if k1:
        out[:k1] = pr.drive_stats(u[:k1], var[:k1])[0]
    if k1 < N:
        if not np.any(var[-1] > 0):
            out[k1:] = pr._nonlinear(u[k1:])
            return out
        for j in range(m):
            col = u[:, j]
            lo, hi = float(col.min()), float(col.max())
            knots = np.concatenate([e.knots()[j] for e in pr._nonlin])
            grid = np.unique(np.concatenate([np.linspace(lo, hi, 16385), knots[(knots > lo) & (knots < hi)]]))
            ug = np.zeros((grid.size, m))
            ug[:, j] = grid
            vg = np.broadcast_to(var[-1], (grid.size, m))
            mean_g = pr.drive_stats(ug, vg)[0][:, j]
            # interpolated in sorted order (np.interp's search is ~15x slower on an oscillating
            # command, whose neighbours rarely share a cell); the order is the record's, cached
            order = _sort_order(col)
            vals = np.empty(N)
            vals[order] = np.interp(col[order], grid, mean_g)
            out[k1:, j] = vals[k1:]
    return out


_ORDERS = Memo(5, flush=True)


def _sort_order(col: np.ndarray) -> np.ndarray:
    """argsort of a command column, cached by content (the recorded command is the same in every
    evaluation of a diagnosis): keyed by a digest of all its bytes (one O(N) pass, against the sort's
    O(N log N))."""
    key = (col.size, hashlib.blake2b(np.ascontiguousarray(col).tobytes(), digest_size=16).digest())
    return _ORDERS.get_or_compute(key, lambda: np.argsort(col, kind="stable"))
