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


class SchurPropagator:
    """x_{k+1} = A_d x_k + r_k over blocks, carrying the state between calls."""

    def __init__(self, Ad: np.ndarray, x0: np.ndarray):
        T, Q = schur(Ad.astype(complex), output="complex")
        self.T, self.Q, self.Qh = T, Q, Q.conj().T
        self.w = x0.astype(complex) @ self.Qh.T        # (trials, n)

    def run(self, r: np.ndarray) -> np.ndarray:
        """r (trials, N, n) -> states x_k (trials, N, n) for the N samples of the block."""
        T = self.T
        n = T.shape[0]
        v = r @ self.Qh.T
        w = np.empty_like(v)
        for i in range(n - 1, -1, -1):
            inp = v[..., i]
            for j in range(i + 1, n):
                if T[i, j] != 0:
                    inp = inp + T[i, j] * w[..., j]
            nxt, _ = lfilter([1.0], [1.0, -T[i, i]], inp, axis=-1, zi=(T[i, i] * self.w[:, i])[:, None])
            w[..., i] = np.concatenate([self.w[:, i:i + 1], nxt[:, :-1]], axis=1)
            self.w[:, i] = nxt[:, -1]
        return (w @ self.Q.T).real


def propagate(Ad: np.ndarray, r: np.ndarray, x0: np.ndarray | None = None) -> np.ndarray:
    """States of x_{k+1} = A_d x_k + r_k for k = 0..N-1 (x_0 = x0, default 0); r (..., N, n)."""
    r3 = r.reshape((-1,) + r.shape[-2:])
    x0 = np.zeros((r3.shape[0], Ad.shape[0])) if x0 is None else np.broadcast_to(x0, (r3.shape[0], Ad.shape[0]))
    return SchurPropagator(Ad, x0).run(r3).reshape(r.shape)


def _command_block(model, command, k0, n, trials):
    if command is None:
        u = model.command.values(k0, n, model.Ts)
        return np.broadcast_to(u, (trials, n, model.m))
    return np.broadcast_to(command[..., k0:k0 + n, :] if command.ndim == 3 else command[k0:k0 + n], (trials, n, model.m))


def simulate(model, n: int, *, seed=None, trials: int | None = None, command=None, normals=None,
             block: int = 1 << 16) -> Record:
    """Simulate ``n`` samples (batch API); ``trials`` independent records when given."""
    return _concat(list(simulate_blocks(model, n, seed=seed, trials=trials, command=command,
                                        normals=normals, block=block)), squeeze=trials is None)


def _concat(parts, squeeze):
    t = np.concatenate([p.t for p in parts])
    cat = {f: np.concatenate([getattr(p, f) for p in parts], axis=1) for f in ("x", "u", "drive", "y")}
    if squeeze:
        cat = {k: v[0] for k, v in cat.items()}
    return Record(t=t, **cat)


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
    states = {eff.id: eff.init_state(static, tr) for eff in model.effects.values()}
    prop = SchurPropagator(model.Ad, np.zeros((tr, model.n_x)))
    act = [e for e in model.effects.values() if hasattr(e, "actuator_batch")]
    sen = [e for e in model.effects.values() if hasattr(e, "sensor_batch")]
    slots = {eff.id: sl for eff, sl in model.normal_layout}
    jitter = "sensor.jitter" in model.effects
    CyAc, CyBc = model.Cy @ model.Ac, model.Cy @ model.Bc
    n_plant = model.plant.n
    for k0 in range(0, n, block):
        nb = min(block, n - k0)
        eps = stream.standard_normal((tr, nb, model.n_normals)) if normals is None \
            else normals[:, k0:k0 + nb, :]
        u = np.array(_command_block(model, command, k0, nb, tr))
        drive = u
        for eff in act:
            drive = eff.actuator_batch(drive, eps[..., slots[eff.id]] if eff.id in slots else None,
                                       states[eff.id])
        r = drive @ model.Bd.T
        if "process.white" in slots:
            r = r + eps[..., slots["process.white"]] @ model.S_proc.T
        x = prop.run(r)
        y = (x @ model.Cy.T + drive @ model.Dy.T) * model.out_gain
        ydot = (x @ CyAc.T + drive @ CyBc.T) * model.out_gain if jitter else None
        for eff in sen:
            y = eff.sensor_batch(y, eps[..., slots[eff.id]] if eff.id in slots else None, states[eff.id], ydot)
        t = np.arange(k0, k0 + nb) * model.Ts
        yield Record(t=t, x=x[..., :n_plant], u=u, drive=drive, y=y)


class Stepper:
    """One sample per call (the real-time loop). ``step(u)`` returns (t, x, u, y) of sample k and
    advances to k+1; ``u`` is the command u_c,k (None: the model's own command generator)."""

    BUFFER = 4096

    def __init__(self, model, seed=None, normals=None):
        self.model = model
        self.k = 0
        self._stream, static = _rngs(seed)
        self._normals = None if normals is None else np.asarray(normals, float).reshape(-1, model.n_normals)
        self._buf = np.empty((0, model.n_normals))
        self._pos = 0
        self.states = {eff.id: eff.init_state(static, 1) for eff in model.effects.values()}
        self.x = np.zeros((1, model.n_x))
        m = model
        self._act = [(e.actuator_step, m.normal_layout_slot(e), self.states[e.id])
                     for e in m.effects.values() if hasattr(e, "actuator_step")]
        self._sen = [(e.sensor_step, m.normal_layout_slot(e), self.states[e.id])
                     for e in m.effects.values() if hasattr(e, "sensor_step")]
        self._proc = m.normal_layout_slot(m.effects["process.white"]) if "process.white" in m.effects else None
        self._jit = "sensor.jitter" in m.effects
        # one product per sample: [x_k, drive_k, e_proc,k] @ M = [x_{k+1}, y_k (plant part), ydot_k]
        nx, p = m.n_x, m.p
        blocks = [[m.Ad.T, m.Cy.T * m.out_gain, (m.Cy @ m.Ac).T * m.out_gain],
                  [m.Bd.T, m.Dy.T * m.out_gain, (m.Cy @ m.Bc).T * m.out_gain]]
        if self._proc is not None:
            blocks.append([m.S_proc.T, np.zeros((m.S_proc.shape[1], p)), np.zeros((m.S_proc.shape[1], p))])
        if not self._jit:
            blocks = [b[:2] for b in blocks]
        self._M = np.block(blocks)
        self._nx, self._p = nx, p
        self._np = m.plant.n
        self._cmd_k0, self._cmd = 0, np.empty((0, m.m))

    def _draw(self) -> np.ndarray:
        if self._pos >= self._buf.shape[0]:
            if self._normals is not None:
                self._buf = self._normals[self.k:self.k + self.BUFFER]
                if self._buf.shape[0] == 0:
                    raise ModelError("the given normals are exhausted")
            else:
                self._buf = self._stream.standard_normal((self.BUFFER, self.model.n_normals))
            self._pos = 0
        e = self._buf[self._pos:self._pos + 1]
        self._pos += 1
        return e

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
        e = self._draw()
        if u is None:
            u = self._command()
        else:
            u = np.asarray(u, float).reshape(1, m.m)
        drive = u
        for fn, sl, st in self._act:
            drive = fn(drive, None if sl is None else e[:, sl], st)
        x = self.x
        z = (x, drive, e[:, self._proc]) if self._proc is not None else (x, drive)
        out = np.concatenate(z, axis=1) @ self._M
        nxt = out[:, :self._nx]
        y = out[:, self._nx:self._nx + self._p]
        ydot = out[:, self._nx + self._p:] if self._jit else None
        for fn, sl, st in self._sen:
            y = fn(y, None if sl is None else e[:, sl], st, ydot)
        self.x = nxt
        self.k = k + 1
        return k * m.Ts, x[0, :self._np], u[0], y[0]
