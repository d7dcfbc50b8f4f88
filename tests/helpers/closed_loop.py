"""Closed-loop records offline for the diagnosis tests: a model's plant and noises stepped one
sample at a time under the reference controller's discrete PID on the measurement
(:func:`noiselab.model.controller.simulate_closed_loop`: the answer to y_k applied from sample
k + 1, as over the wire), the applied command recorded."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from noiselab.model.controller import ControllerSpec, simulate_closed_loop


@dataclass
class Record:
    t: np.ndarray
    y: np.ndarray
    u: np.ndarray


def spec(kp: float, ki: float, kd: float, ref: str = "none", amplitude: float = 0.0,
         frequency_hz: float = 0.0) -> ControllerSpec:
    """The PID and its reference (none, step or sine)."""
    return ControllerSpec(kp, ki, kd, reference=ref, amplitude=amplitude if ref != "none" else 0.0,
                          frequency_hz=frequency_hz if ref == "sine" else 0.0)


def closed_loop(model, n: int, kp: float, ki: float, kd: float, seed: int, ref: str = "none",
                amplitude: float = 0.0, frequency_hz: float = 0.0) -> Record:
    """n samples of ``model`` (one input, one output, command external) under the PID."""
    out = simulate_closed_loop(model, n, seed=seed, spec=spec(kp, ki, kd, ref, amplitude, frequency_hz))
    return Record(out["t"], out["y"], out["u"])


def controlled(model, n: int, seed: int) -> Record:
    """n samples of ``model`` under its own ``[controller]``."""
    out = simulate_closed_loop(model, n, seed=seed)
    return Record(out["t"], out["y"], out["u"])
