"""``sensor.jitter``: the sampling instant is t_k + dt_k, dt_k ~ N(0, std_s^2) white.

First-order Taylor (seed section 6.3): y(t_k + dt_k) ~ y(t_k) + ydot(t_k) dt_k, with ydot from the
continuous plant, (1 + s_f) C (A x_k + B drive_k) (+ D drive rate, neglected: the drive is held).
The error is white but its variance depends on the signal, Var(n_j,k) = E[ydot_k^2] std_s^2;
predictions use the time average of E[ydot_k^2] over the record. One dt_k per sample (all outputs
are sampled at the same instant). Valid while std_s is small against the plant's time scales.
"""

from __future__ import annotations

import numpy as np

from .base import Effect, FitSpec, _g


class SensorJitter(Effect):
    id = "sensor.jitter"
    stage = "sensor"
    chain_order = 11
    draw_order = 6
    linear = False
    summary = "sampling-time jitter"
    fit = FitSpec("modulated", scale="std_s", unit_scale="Ts/10", needs_command=True)

    @classmethod
    def explain(cls, params, Ts, ctx=None):
        return (f"the residual's high-frequency power rises and falls with the square of the signal's "
                f"slope (largest where the response is steepest): sampling-time jitter of about "
                f"{_g(np.asarray(params['std_s']) * 1e6)} us rms")

    def parse(self, t):
        self.params["std_s"] = t.number("std_s", check=lambda v: 0 <= v < self.dims.Ts,
                                        expect=f"a std in s, 0 <= std_s < Ts = {self.dims.Ts:g}")

    def n_normals(self):
        return 1

    def time_errors(self, e):
        """dt_k = std_s e_k (s) for a block of normals; the error added to y_k is ydot_k dt_k."""
        return self.params["std_s"] * e

    def spectral(self, mean_sq_ydot=None):
        # filled in by the predictor, which knows E[ydot^2]
        return [("jitter", self.params["std_s"] ** 2)]

    # -- prediction hooks (:mod:`.base`) ----------------------------------------------------------
    signal_dependent = True           # its variance is std_s^2 E[ydot^2] over the command
    without_plant = ("a sampling-time error dt shows as dy/dt * dt, and the reference is held over each sample "
                     "(dy/dt = 0 between samples), so it adds nothing")

    def approximation_note(self, avg, others_var):
        return ("sensor.jitter: first-order Taylor, variance std_s^2 E[ydot^2] averaged over "
                f"{avg.span_s:.3g} s of the model's command")
