"""The plant: a continuous LTI system x' = A x + B u + L w, y = C x + D u.

The ``[plant]`` table is either the mass-spring-damper shorthand (``m``, ``c``, ``k``: x = [position,
velocity], y = position, force input, process noise enters as a force, L = B) or a general
continuous plant given by ``A``, ``B``, ``C`` (and optional ``D``, and ``L`` = process-noise input,
default ``B``). Several rows of C give a vector measurement.

A model without ``[plant]`` (a sensor alone: a gyro at rest, an accelerometer axis) has the plant
of :func:`no_plant`: no states (n = 0) and a unit feedthrough, y = D u with D = I (m = p), so the
command is the reference each output measures and every path (discretization, simulation,
predictions, diagnosis) runs on it unchanged. Nothing drives a state there: it has no process
noise input (nw = 0), and :attr:`Plant.has_states` is how the rest of the code tells it apart.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .schema import Table


@dataclass(frozen=True)
class Plant:
    A: np.ndarray   # (n, n)  state matrix, 1/s
    B: np.ndarray   # (n, m)  input matrix
    C: np.ndarray   # (p, n)  output matrix
    D: np.ndarray   # (p, m)  feedthrough
    L: np.ndarray   # (n, nw) process-noise input matrix
    state_names: tuple[str, ...]

    @property
    def n(self) -> int:
        return self.A.shape[0]

    @property
    def has_states(self) -> bool:
        """False for the plant of a sensor-only model (:func:`no_plant`): no [plant] table."""
        return self.n > 0

    @property
    def m(self) -> int:
        return self.B.shape[1]

    @property
    def p(self) -> int:
        return self.C.shape[0]

    @property
    def nw(self) -> int:
        return self.L.shape[1]


def no_plant(p: int) -> Plant:
    """The plant of a sensor-only model of ``p`` outputs: y_k = u_k, the reference (the command,
    in the outputs' units) passed through unchanged; A (0, 0), B (0, p), C (p, 0), D = I_p, L (0, 0).
    A model file cannot write it (a matrix there has at least one entry): it is the absence of
    [plant]."""
    return Plant(np.zeros((0, 0)), np.zeros((0, p)), np.zeros((p, 0)), np.eye(p), np.zeros((0, 0)), ())


def parse_plant(t: Table) -> Plant:
    if t.has("A") or t.has("B") or t.has("C"):
        for key in ("m", "c", "k"):
            if t.has(key):
                raise t.error(key, "give either the mass-spring-damper shorthand (m, c, k) or A, B, C, not both")
        A = t.matrix("A")
        n = A.shape[0]
        if A.shape[1] != n:
            raise t.error("A", f"expected a square matrix, got {A.shape[0]} x {A.shape[1]}")
        B = t.matrix("B", rows=n)
        m = B.shape[1]
        C = t.matrix("C", cols=n)
        p = C.shape[0]
        D = t.matrix("D", None, rows=p, cols=m)
        D = np.zeros((p, m)) if D is None else D
        L = t.matrix("L", None, rows=n)
        L = B.copy() if L is None else L
        t.done()
        return Plant(A, B, C, D, L, tuple(f"x{i}" for i in range(n)))
    mass = t.number("m", check=lambda v: v > 0, expect="a mass in kg > 0")
    c = t.number("c", check=lambda v: v >= 0, expect="a damping in N s/m >= 0")
    k = t.number("k", check=lambda v: v >= 0, expect="a stiffness in N/m >= 0")
    t.done()
    A = np.array([[0.0, 1.0], [-k / mass, -c / mass]])
    B = np.array([[0.0], [1.0 / mass]])
    C = np.array([[1.0, 0.0]])
    return Plant(A, B, C, np.zeros((1, 1)), B.copy(), ("position", "velocity"))
