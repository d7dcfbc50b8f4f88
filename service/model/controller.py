"""A reference controller for a model whose command is ``external``: the optional
``[controller]`` table of a model file, the discrete PID law the controller node runs, and the
closed loop's poles (pure math; the node is :mod:`noiselab.nodes.controller`).

The model file::

    [controller]            # only with [command] kind = "external", one input and one output
    kind = "pid"
    kp = 8.0                # N/m            (input units per output unit)
    ki = 4.0                # N/(m s)
    kd = 2.0                # N s/m
    reference = "sine"      # none (r = 0) | step (r = amplitude from t = 0) | sine (amplitude sin(2 pi f t))
    amplitude = 0.2         # m, > 0 (step, sine)
    frequency_hz = 0.2      # Hz, > 0 (sine)

The law, at the model's Ts, for the measurement y_k of sample k (time t_k = k Ts) and the
reference r_k = r(t_k)::

    e_k = r_k - y_k
    I_k = I_{k-1} + ki Ts e_k                       (I_{-1} = 0; rectangle rule, e_k included)
    D_k = -kd (y_k - y_j) / ((k - j) Ts)             (j: the previous measurement; D = 0 at the first)
    u_k = kp e_k + I_k + D_k

Derivative on the measurement, not on the error: a step or a fast sine in r would put r's
difference quotient, kd Delta r / Ts (a kick of 40 N for a 0.2 m step at kd = 2, Ts = 0.01), into
the command; on the measurement the derivative sees the plant's motion (and the sensor's noise,
as it would on the error). The controller answers y_k with u_k, which the emulator's zero-order
hold applies from the next sample it steps (k + 1 when the answer is on time): the loop has at
least one sample of delay, and :func:`closed_loop_matrix` takes it (and longer ones) into account.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import ModelError
from .schema import Table

KINDS = ("pid",)
REFERENCES = ("none", "step", "sine")


@dataclass(frozen=True)
class ControllerSpec:
    """A PID controller and its reference (see the module docstring)."""

    kp: float
    ki: float
    kd: float
    reference: str = "none"
    amplitude: float = 0.0
    frequency_hz: float = 0.0
    kind: str = "pid"

    def r(self, t: float) -> float:
        """The reference at stream time ``t`` (s)."""
        if self.reference == "step":
            return self.amplitude
        if self.reference == "sine":
            return self.amplitude * math.sin(2.0 * math.pi * self.frequency_hz * t)
        return 0.0

    def to_dict(self) -> dict:
        """The ``[controller]`` table as the model file writes it."""
        d: dict = {"kind": self.kind, "kp": self.kp, "ki": self.ki, "kd": self.kd, "reference": self.reference}
        if self.reference in ("step", "sine"):
            d["amplitude"] = self.amplitude
        if self.reference == "sine":
            d["frequency_hz"] = self.frequency_hz
        return d


def parse_controller(t: Table | None, command_kind: str, m: int, p: int) -> ControllerSpec | None:
    """The ``[controller]`` table (None when absent), validated with one-line errors."""
    if t is None:
        return None
    if command_kind != "external":
        raise t.error(None, f"a controller needs [command] kind = \"external\" (its output is the command), "
                            f"got kind = {command_kind!r}")
    if (m, p) != (1, 1):
        raise t.error(None, f"a PID controller needs a plant with one input and one output, got {m} and {p}")
    t.string("kind", choices=KINDS)
    gains = [t.number(name) for name in ("kp", "ki", "kd")]
    reference = t.string("reference", "none", choices=REFERENCES)
    amplitude = t.number("amplitude", check=lambda v: v > 0, expect="an amplitude > 0") \
        if reference in ("step", "sine") else 0.0
    freq = t.number("frequency_hz", check=lambda v: v > 0, expect="a frequency in Hz > 0") \
        if reference == "sine" else 0.0
    t.done()
    return ControllerSpec(*gains, reference=reference, amplitude=amplitude, frequency_hz=freq)


class Pid:
    """The discrete PID law of the module docstring, one measurement at a time."""

    def __init__(self, spec: ControllerSpec, Ts: float):
        self.spec, self.Ts = spec, Ts
        self.integral = 0.0
        self.last: tuple[int, float] | None = None      # (seq, y) of the previous measurement

    def step(self, seq: int, t: float, y: float) -> float:
        """u_k for measurement ``y`` (seq k, time ``t`` s); ``seq`` past the previous one's."""
        s = self.spec
        e = s.r(t) - y
        self.integral += s.ki * self.Ts * e
        d = 0.0
        if self.last is not None:
            j, y_j = self.last
            d = -s.kd * (y - y_j) / ((seq - j) * self.Ts)
        self.last = (seq, y)
        return s.kp * e + self.integral + d


def closed_loop_matrix(model, spec: ControllerSpec, delay: int = 1) -> np.ndarray:
    """The state matrix of the noise-free loop, model (discretized plant, lag states, sensor
    gain) and PID with r = 0, the answer to y_k applied at sample k + ``delay`` (>= 1).

    State z_k = [x_k, u_k, u_{k+1} ... u_{k+delay-1} (queued answers), I_{k-1}, y_{k-1}]:
    x_{k+1} = Ad x_k + Bd u_k, y_k = g (C x_k + D u_k), I_k = I_{k-1} - ki Ts y_k,
    u_{k+delay} = -(kp + ki Ts) y_k + I_{k-1} - kd (y_k - y_{k-1}) / Ts."""
    if model.m != 1 or model.p != 1 or delay < 1:
        raise ModelError("closed_loop_matrix: one input, one output and delay >= 1")
    Ad, Bd, Ts = model.Ad, model.Bd[:, 0], model.Ts
    n = Ad.shape[0]
    cy = np.zeros(n + delay + 2)                       # y_k as a row on z_k
    cy[:n] = model.out_gain[0] * model.Cy[0]
    cy[n] = model.out_gain[0] * model.Dy[0, 0]
    N = n + delay + 2
    iI, iy = n + delay, n + delay + 1
    A = np.zeros((N, N))
    A[:n, :n], A[:n, n] = Ad, Bd
    for j in range(delay - 1):                        # the queue moves up by one sample
        A[n + j, n + j + 1] = 1.0
    g = spec.kp + spec.ki * Ts + spec.kd / Ts
    A[n + delay - 1] = -g * cy
    A[n + delay - 1, iI] += 1.0
    A[n + delay - 1, iy] += spec.kd / Ts
    A[iI] = -spec.ki * Ts * cy
    A[iI, iI] += 1.0
    A[iy] = cy
    return A


def closed_loop_poles(model, spec: ControllerSpec, delay: int = 1) -> np.ndarray:
    """Eigenvalues of :func:`closed_loop_matrix` (stable: all inside the unit circle). Without
    integral action (ki = 0) the integral's state stays at zero, outside the loop: its eigenvalue
    1 is not a pole of the loop and is left out (a PD read as marginally stable otherwise)."""
    A = closed_loop_matrix(model, spec, delay)
    if spec.ki == 0.0:
        keep = np.arange(A.shape[0]) != A.shape[0] - 2           # the state I_{k-1}
        A = A[np.ix_(keep, keep)]
    return np.linalg.eigvals(A)


def simulate_closed_loop(model, n: int, *, seed=None, spec: ControllerSpec | None = None, delay: int = 1) -> dict:
    """The loop offline: ``model`` stepped as the emulator steps it (its step API, the same seed
    gives the same noises), under ``spec`` (default the model's ``[controller]``), every answer
    applied ``delay`` samples after its measurement (1: on time, as a live run whose controller
    is never late). Returns {"t", "x", "u" (applied), "y", "control" (the answers)}: arrays of
    ``n`` rows; ``model.simulate(n, seed=seed, command=u)`` gives the same ``y``."""
    spec = spec or model.controller
    if spec is None or model.m != 1 or model.p != 1 or delay < 1:
        raise ModelError(f"{model.source}: simulate_closed_loop needs a controller, one input and one output, "
                         "and delay >= 1")
    stepper, pid = model.stepper(seed=seed), Pid(spec, model.Ts)
    queue = [0.0] * delay                          # zero until the first answer is applied
    rows = []
    for k in range(n):
        t, x, u, y = stepper.step([queue.pop(0)])
        c = pid.step(k, t, float(y[0]))
        queue.append(c)
        rows.append((t, x, u, y, c))
    t, x, u, y, c = zip(*rows) if rows else ((),) * 5
    return {"t": np.array(t), "x": np.array(x).reshape(n, -1), "u": np.array(u).reshape(n, 1),
            "y": np.array(y).reshape(n, 1), "control": np.array(c)}
