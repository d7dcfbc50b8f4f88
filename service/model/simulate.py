"""Simulation: a batch API (whole records and Monte Carlo ensembles) and a step API (one sample at
a time, for the real-time loop). Both follow the signal chain of :mod:`.effects.base` and consume
the same standard normals, so for the same seed they give the same sample path: the first-order
stages (AR(1), bias states, sums) to the last bit, the plant to floating-point rounding (the batch
path runs it in complex Schur coordinates, the step path in the original ones).

Randomness is explicit: ``seed`` (int or SeedSequence) is split by ``SeedSequence.spawn(2)`` into
the per-sample stream (a block of ``model.n_normals`` standard normals per sample, effects in
draw order) and a static stream (tone phases, initial biases). ``normals`` replaces the per-sample
stream by given draws (shape (N, n_normals) or (trials, N, n_normals)), e.g. to replay the seed
lesson's own random numbers.

Batch plant propagation: with A_d = Q T Q^H (complex Schur, Q unitary, T upper triangular) the
state w = Q^H x obeys w_{k+1} = T w_k + Q^H r_k; solved from the last coordinate up, each is the
first-order recursion w_i,k+1 = T_ii w_i,k + (Q^H r_k + sum_{j>i} T_ij w_j,k)_i, run by
scipy.signal.lfilter. Unitary, so as well conditioned as A_d itself; defective A_d is fine.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import schur
from scipy.signal import lfilter

from .errors import ModelError

COND_MAX = 1e8           # eigenvector condition number beyond which lsim uses the Schur propagator


@dataclass
class Record:
    """A simulated record. Arrays have a leading trial axis when ``trials`` was given.

    t (N,) s; x (.., N, n) plant state (without lag states); u (.., N, m) command u_c;
    drive (.., N, m) the plant input after actuator effects; y (.., N, p) measurement.
    """

    t: np.ndarray
    x: np.ndarray
    u: np.ndarray
    drive: np.ndarray
    y: np.ndarray


def _rngs(seed):
    ss = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
    stream, static = ss.spawn(2)
    return np.random.default_rng(stream), np.random.default_rng(static)


def _mul(X: np.ndarray, M: np.ndarray) -> np.ndarray:
    """X @ M for a small M (k, n) as explicit sums over k: no BLAS call, so no thread pool on
    these skinny products (measured: multithreaded BLAS made them 3-10x slower on 2 busy cores).
    k = 0 (a sensor-only model's empty state) gives zeros."""
    if M.shape[0] == 0:
        return np.zeros(X.shape[:-1] + M.shape[1:], np.result_type(X, M))
    out = X[..., 0, None] * M[0]
    for i in range(1, M.shape[0]):
        out = out + X[..., i, None] * M[i]
    return out


class SchurPropagator:
    """x_{k+1} = A_d x_k + r_k over blocks, carrying the state between calls."""

    def __init__(self, Ad: np.ndarray, x0: np.ndarray):
        T, Q = schur(Ad.astype(complex), output="complex")
        self.T, self.Q, self.Qh = T, Q, Q.conj().T
        self.w = _mul(x0.astype(complex), self.Qh.T)        # (trials, n)

    def run(self, r: np.ndarray) -> np.ndarray:
        """r (trials, N, n) -> states x_k (trials, N, n) for the N samples of the block."""
        T = self.T
        n = T.shape[0]
        if n == 0:
            return np.zeros(r.shape)
        v = _mul(r.astype(complex), self.Qh.T)
        w = np.empty_like(v)
        for i in range(n - 1, -1, -1):
            inp = v[..., i]
            for j in range(i + 1, n):
                if T[i, j] != 0:
                    inp = inp + T[i, j] * w[..., j]
            nxt, _ = lfilter([1.0], [1.0, -T[i, i]], inp, axis=-1, zi=(T[i, i] * self.w[:, i])[:, None])
            w[..., 0, i] = self.w[:, i]
            w[..., 1:, i] = nxt[:, :-1]
            self.w[:, i] = nxt[:, -1]
        return _mul(w, self.Q.T).real.copy()


def propagate(Ad: np.ndarray, r: np.ndarray, x0: np.ndarray | None = None) -> np.ndarray:
    """States of x_{k+1} = A_d x_k + r_k for k = 0..N-1 (x_0 = x0, default 0); r (..., N, n)."""
    r3 = r.reshape((-1,) + r.shape[-2:])
    x0 = np.zeros((r3.shape[0], Ad.shape[0])) if x0 is None else np.broadcast_to(x0, (r3.shape[0], Ad.shape[0]))
    return SchurPropagator(Ad, x0).run(r3).reshape(r.shape)


def _add_outer(y: np.ndarray, s: np.ndarray, g: np.ndarray) -> None:
    """y += outer(s, g) a column at a time, the same sums without the (N, p) temporary (4x faster
    on 10^6 samples: the temporary's pages cost more than the arithmetic)."""
    for j in range(g.size):
        y[:, j] += s * g[j]


def lsim(Ad: np.ndarray, Bd: np.ndarray, C: np.ndarray, D: np.ndarray, u: np.ndarray) -> np.ndarray:
    """y_k = C x_k + D u_k, x_{k+1} = Ad x_k + Bd u_k, x_0 = 0; u (N, m) -> y (N, p).

    Modal, in real arithmetic: one first-order recursion per real eigenvalue and one second-order
    section per conjugate pair (lfilter), several times faster than the complex Schur propagator
    on long records. Falls back to :func:`propagate` when Ad's eigenvectors are ill-conditioned."""
    u = np.asarray(u, float)
    N = u.shape[0]
    y = u @ D.T if D.size else np.zeros((N, C.shape[0]))
    n = Ad.shape[0]
    if n == 0:
        return y
    lam, V = np.linalg.eig(Ad)
    if np.linalg.cond(V) > COND_MAX:
        x = propagate(Ad, u @ Bd.T)
        return y + x @ C.T
    Vi = np.linalg.inv(V)
    Bm = Vi @ Bd                       # (n, m)
    Cm = C @ V                         # (p, n)
    done = np.zeros(n, bool)
    for i in range(n):
        if done[i]:
            continue
        done[i] = True
        lam_i = complex(lam[i])
        j = []
        if abs(lam_i.imag) > 0:
            # its conjugate partner: the pair is one real second-order section
            j = [k for k in range(n) if not done[k] and np.isclose(lam[k], np.conj(lam_i), rtol=1e-10, atol=1e-14)]
            if j:
                done[j[0]] = True
        for c in range(u.shape[1]):
            g = Cm[:, i] * Bm[i, c]                      # (p,) output weights of this mode and input
            if not np.any(g) or not np.any(u[:, c]):
                continue
            if j:
                # g z^-1 / (1 - lam z^-1) + conj: (2 Re g z^-1 - 2 Re(g conj lam) z^-2) / (1 - 2 Re lam z^-1 + |lam|^2 z^-2)
                s_ = lfilter([1.0], [1.0, -2.0 * lam_i.real, abs(lam_i) ** 2], u[:, c])
                b1, b2 = 2.0 * g.real, -2.0 * (g * np.conj(lam_i)).real
                _add_outer(y[1:], s_[:-1], b1)
                _add_outer(y[2:], s_[:-2], b2)
            elif lam_i.imag == 0:
                # x_k = sum_{l<k} lam^(k-1-l) u_l (a real mode: g real up to rounding)
                s_ = lfilter([1.0], [1.0, -lam_i.real], u[:, c])
                _add_outer(y[1:], s_[:-1], g.real)
            else:                      # a complex mode without its partner (not from a real A): as is
                z = lfilter([0.0, 1.0], [1.0, -lam_i], u[:, c].astype(complex))
                y += np.outer(z, g).real
    return y


def _command_block(model, command, k0, n, trials):
    if command is None:
        u = model.command.values(k0, n, model.Ts)
        return np.broadcast_to(u, (trials, n, model.m))
    return np.broadcast_to(command[..., k0:k0 + n, :] if command.ndim == 3 else command[k0:k0 + n], (trials, n, model.m))


def simulate(model, n: int, *, seed=None, trials: int | None = None, command=None, normals=None,
             block: int = 1 << 16) -> Record:
    """Simulate ``n`` samples (batch API); ``trials`` independent records when given. The
    output arrays are allocated once and filled block by block (memory ~ the outputs)."""
    tr = 1 if trials is None else int(trials)
    out = None
    for blk in simulate_blocks(model, n, seed=seed, trials=trials, command=command, normals=normals, block=block):
        if out is None:
            out = {f: np.empty((tr, n) + getattr(blk, f).shape[2:]) for f in ("x", "u", "drive", "y")}
            k0 = 0
        nb = blk.t.size
        for f in out:
            out[f][:, k0:k0 + nb] = getattr(blk, f)
        k0 += nb
    if trials is None:
        out = {k: v[0] for k, v in out.items()}
    return Record(t=np.arange(n) * model.Ts, **out)


class _Chain:
    """The signal chain of one model, shared by the batch and step paths (same functions, same
    order of floating-point operations)."""

    def __init__(self, model, static, trials):
        self.model = model
        self.states = {eff.id: eff.init_state(static, trials) for eff in model.effects.values()}
        self.slots = {eff.id: sl for eff, sl in model.normal_layout}
        eff = model.effects.values()
        self.act_src = [e for e in eff if hasattr(e, "actuator_terms")]
        self.act_nl = [e for e in eff if e.stage == "actuator" and hasattr(e, "apply")]
        self.sen_src = [e for e in eff if hasattr(e, "sensor_terms")]
        # sampling-time errors (``time_errors``), static maps of the measurement after the sum
        # (``acts_after_sum``), and the normals of the state-noise sources (columns of S_proc)
        self.timing = [e for e in eff if hasattr(e, "time_errors")]
        self.out_maps = [e for e in eff if e.acts_after_sum]
        self.out_filter = next((e for e in eff if hasattr(e, "filter_terms")), None)
        procs = [self.slots[e.id] for e in model.proc_sources if e.id in self.slots]
        self.proc = None if not procs else procs[0] if len(procs) == 1 else \
            np.concatenate([np.arange(sl.start, sl.stop) for sl in procs])

    def noise_terms(self, eps):
        """State-independent terms for a block of normals: actuator noises (trials, n, m) each,
        sensor additive terms (trials, n, p) each, jitter time errors (trials, n, 1)."""
        n = eps.shape[1]
        act = [e.actuator_terms(eps[..., self.slots[e.id]], self.states[e.id]) for e in self.act_src]
        sen = []
        for e in self.sen_src:
            if e.id in self.slots:
                sen.append(e.sensor_terms(eps[..., self.slots[e.id]], self.states[e.id]))
            else:
                sen.append(e.sensor_terms(None, self.states[e.id], n))
        dt = sum(e.time_errors(eps[..., self.slots[e.id]]) for e in self.timing) if self.timing else None
        if self.out_filter is not None and sen:
            # the sensor's own filter acts on the sources before it (all of them: chain orders 7-10)
            sen = [self.out_filter.filter_terms(sum(sen[1:], sen[0]), self.states[self.out_filter.id])]
        return act, sen, dt


def simulate_blocks(model, n: int, *, seed=None, trials: int | None = None, command=None, normals=None,
                    block: int = 1 << 16):
    """Generator of consecutive :class:`Record` blocks (leading trial axis), bounded memory."""
    if n < 1:
        raise ModelError(f"number of samples must be >= 1, got {n}")
    tr = 1 if trials is None else int(trials)
    stream, static = _rngs(seed)
    if command is not None:
        command = np.asarray(command, float)
        if command.ndim == 1:
            command = command[:, None]
        if command.shape[-2] < n or command.shape[-1] != model.m:
            raise ModelError(f"command must have shape ({n}, {model.m}), got {command.shape}")
    if normals is not None:
        normals = np.asarray(normals, float)
        if normals.ndim == 2:
            normals = normals[None]
        if normals.shape[1] < n or normals.shape[2] != model.n_normals or normals.shape[0] != tr:
            raise ModelError(f"normals must have shape ({tr}, {n}, {model.n_normals}), got {normals.shape}")
    chain = _Chain(model, static, tr)
    prop = SchurPropagator(model.Ad, np.zeros((tr, model.n_x)))
    CyAc, CyBc = model.Cy @ model.Ac, model.Cy @ model.Bc
    n_plant = model.plant.n
    for k0 in range(0, n, block):
        nb = min(block, n - k0)
        eps = stream.standard_normal((tr, nb, model.n_normals)) if normals is None \
            else normals[:, k0:k0 + nb, :]
        act, sen, dt = chain.noise_terms(eps)
        u = np.array(_command_block(model, command, k0, nb, tr))
        drive = u
        for term in act:
            drive = drive + term
        for e in chain.act_nl:
            drive = e.apply(drive)
        r = _mul(drive, model.Bd.T)
        if chain.proc is not None:
            r = r + _mul(eps[..., chain.proc], model.S_proc.T)
        x = prop.run(r)
        y = (_mul(x, model.Cy.T) + _mul(drive, model.Dy.T)) * model.out_gain
        for term in sen:
            y = y + term
        if dt is not None:
            ydot = (_mul(x, CyAc.T) + _mul(drive, CyBc.T)) * model.out_gain
            y = y + ydot * dt
        for e in chain.out_maps:
            y = e.apply(y)
        t = np.arange(k0, k0 + nb) * model.Ts
        yield Record(t=t, x=x[..., :n_plant], u=u, drive=drive, y=y)


class Stepper:
    """One sample per call (the real-time loop). ``step(u)`` returns (t, x, u, y) of sample k and
    advances to k+1; ``u`` is the command u_c,k (None: the model's own command generator).

    Noise sources depend neither on the plant state nor on the command, so they are computed a
    buffer at a time with the batch functions (identical floats); per sample only the drive,
    the nonlinearities, the plant, the jitter and the quantizer remain."""

    BUFFER = 4096

    def __init__(self, model, seed=None, normals=None):
        self.model = model
        self.k = 0
        self._stream, static = _rngs(seed)
        self._normals = None if normals is None else np.asarray(normals, float).reshape(-1, model.n_normals)
        self._chain = _Chain(model, static, 1)
        self._end = 0                       # buffered samples cover k < self._end
        self.x = np.zeros((1, model.n_x))
        m = model
        self._jit = bool(self._chain.timing)
        # one product per sample: [x_k, drive_k, e_proc,k] @ M = [x_{k+1}, y_k (plant part), ydot_k]
        nx, p = m.n_x, m.p
        blocks = [[m.Ad.T, m.Cy.T * m.out_gain, (m.Cy @ m.Ac).T * m.out_gain],
                  [m.Bd.T, m.Dy.T * m.out_gain, (m.Cy @ m.Bc).T * m.out_gain]]
        if self._chain.proc is not None:
            k = m.S_proc.shape[1]
            blocks.append([m.S_proc.T, np.zeros((k, p)), np.zeros((k, p))])
        if not self._jit:
            blocks = [b[:2] for b in blocks]
        self._M = np.block(blocks)
        self._nx, self._p = nx, p
        self._np = m.plant.n
        self._nl = [e.apply for e in self._chain.act_nl]
        self._out_maps = [e.apply for e in self._chain.out_maps]
        self._cmd_k0, self._cmd = 0, np.empty((0, m.m))

    def _refill(self) -> None:
        m = self.model
        if self._normals is not None:
            eps = self._normals[self.k:self.k + self.BUFFER]
            if eps.shape[0] == 0:
                raise ModelError("the given normals are exhausted")
        else:
            eps = self._stream.standard_normal((self.BUFFER, m.n_normals))
        act, sen, dt = self._chain.noise_terms(eps[None])
        self._act = [a[0] for a in act]
        self._sen = [s_[0] for s_ in sen]
        self._dt = None if dt is None else dt[0]
        self._proc = None if self._chain.proc is None else eps[:, self._chain.proc]
        self._k0 = self.k
        self._end = self.k + eps.shape[0]

    def _command(self) -> np.ndarray:
        # the command generator is elementwise in k, so blocks give the same floats as one call
        if not (self._cmd_k0 <= self.k < self._cmd_k0 + self._cmd.shape[0]):
            self._cmd_k0 = self.k
            self._cmd = self.model.command.values(self.k, self.BUFFER, self.model.Ts)
        i = self.k - self._cmd_k0
        return self._cmd[i:i + 1]

    def step(self, u=None):
        m = self.model
        k = self.k
        if k >= self._end:
            self._refill()
        i = k - self._k0
        if u is None:
            u = self._command()
        else:
            u = np.asarray(u, float).reshape(1, m.m)
        drive = u
        for a in self._act:
            drive = drive + a[i]
        for f in self._nl:
            drive = f(drive)
        x = self.x
        z = (x, drive, self._proc[i:i + 1]) if self._proc is not None else (x, drive)
        out = np.concatenate(z, axis=1) @ self._M
        y = out[:, self._nx:self._nx + self._p]
        for s_ in self._sen:
            y = y + s_[i]
        if self._jit:
            y = y + out[:, self._nx + self._p:] * self._dt[i]
        for f in self._out_maps:
            y = f(y)
        self.x = out[:, :self._nx]
        self.k = k + 1
        return k * m.Ts, x[0, :self._np], u[0], y[0]
