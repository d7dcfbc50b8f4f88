"""Closed-loop records offline: a model's plant and noises stepped one sample at a time
(:class:`noiselab.model.simulate.Stepper`) under a discrete PID on the measurement, the command
computed from the samples before it (the controller's reply reaches the plant one sample later, as
over the wire: the emulator applies the latest control it has).

    e_k = r_k - y_{k-1},   u_k = kp e_k + ki Ts sum_{i<=k} e_i - kd (y_{k-1} - y_{k-2}) / Ts

(derivative on the measurement: a step of the reference kicks no derivative). The recorded command
is the applied one, u_k."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Record:
    t: np.ndarray
    y: np.ndarray
    u: np.ndarray
    r: np.ndarray


def reference(kind: str, t: np.ndarray, amplitude: float = 0.0, frequency_hz: float = 0.0) -> np.ndarray:
    """r(t): ``none`` (0), ``step`` (amplitude from t = 0), ``sine`` (amplitude sin(2 pi f t))."""
    if kind == "none":
        return np.zeros_like(t)
    if kind == "step":
        return np.full_like(t, amplitude)
    if kind == "sine":
        return amplitude * np.sin(2 * np.pi * frequency_hz * t)
    raise ValueError(f"reference: expected none, step or sine, got {kind!r}")


def closed_loop(model, n: int, kp: float, ki: float, kd: float, seed: int, ref: str = "none",
                amplitude: float = 0.0, frequency_hz: float = 0.0) -> Record:
    """n samples of ``model`` (one input, one output) under the PID above."""
    Ts = model.Ts
    st = model.stepper(seed=seed)
    t = np.arange(n) * Ts
    r = reference(ref, t, amplitude, frequency_hz)
    y = np.zeros(n)
    u = np.zeros(n)
    y1 = y2 = 0.0
    acc = 0.0
    for k in range(n):
        e = r[k] - y1
        acc += e * Ts
        u[k] = kp * e + ki * acc - kd * (y1 - y2) / Ts
        out = st.step(np.array([u[k]]))
        y[k] = float(np.ravel(out[3])[0])
        y2, y1 = y1, y[k]
    return Record(t, y[:, None], u[:, None], r)
