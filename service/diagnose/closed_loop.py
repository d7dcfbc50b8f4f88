"""A record under feedback: whether the recorded command follows past measurements, and which of
its lines the controller copied from the measurement.

Under a controller the command is computed from the measurement: u = K (r - y), and with the plant
y = G u + v (v: every noise and sensor effect, what the diagnosis models) the applied command is

    u = S K r - S K v,          S = (1 + K G)^-1,

a part driven by the reference and a part that is the noise fed back. The residual of the mean
response to the *recorded* command, y - G u = v, is still the noise process, so the likelihood and
the views carry over; but the command is no longer independent of v. Two consequences:

* a line of v (a sensor tone, a vibration) reaches the command through the controller, -S K v at
  its frequency: the rule that a residual line at a command line is the mean response's error (a
  lag, a gain) would refuse it;
* the command's power is partly the noise's: what the recorded command carries because of the
  reference is u_ref = u - F v, with F = -S K the causal filter from v to u.

Detection (Granger's test of v -> u, Granger 1969): the command's broadband part (its own lines
taken out by least squares) is regressed on its own past and on v's past, lags 1..L
(:data:`LAGS`); the partial F statistic of v's L p regressors, at level :data:`ALPHA`, and a
share r2 >= :data:`R2_MIN` of what the command's own past leaves that v's past explains, say the
command follows past measurements. The share is a materiality bar: at N ~ 1e5 the test alone
passes for r2 of a few 1e-4, and a mean-response error whose memory is longer than the lags (a
missing actuator lag under a chirp, its frequency drifting: r2 = 0.25 to 0.5 %, p = 8e-27) carries a
little of the command's own past that its 40 lags do not. A digital controller's command is an
exact function of past measurements (r2 = 1.00 on every closed record of the test families);
open-loop records stay below 0.5 %. An open-loop command (a sine, a chirp, a PRBS, none) is
independent of v's noise, and the mean response's error in v (a wrong gain, a missing lag) is a
function of past commands, which the command's own lags carry: the regression finds nothing beyond
chance. The command regressed on v's past alone estimates F.

A command line at f is fed back when F(f) V(f) (V the residual's complex amplitude at f) accounts
for most of the command's own amplitude U(f): |U - F V| < |U| / 2 (:data:`FED_BACK`). The others
are the reference's.

What only the reference shows (:func:`scale_factor_reach`): with r = 0 the command is the noise fed
back, u = -S K v, and a sensor gain error e leaves e G u in the residual, a filter of the noise
itself, which the noise model's own variances largely absorb: the gain is read from the noise's
shape alone. The record's information on e, from the fitted model's log-likelihood at e = +-h
(observed information I = -(l(h) + l(-h) - 2 l(0)) / h^2, the variances the fit has free refitted
at each),
gives the smallest scale factor the diagnosis would add, 2 Delta l = I e^2 > THRESHOLD + ln n:
e_min = sqrt((THRESHOLD + ln n) / I). It falls as 1 / (the reference's amplitude) where the
reference's response dominates the information (Ljung 1999, sec. 13.4: informative experiments
in closed loop need an excitation from outside the loop).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

REACH_H = 0.05            # the scale factor's trial values +-h about the fitted model (:func:`scale_factor_reach`)
LAGS = 40                 # past samples of the residual the command is regressed on (F's FIR length)
ALPHA = 1e-6              # level of the test that the command follows the measurement
R2_MIN = 0.05            # the least share of the command's broadband part that the measurement's past explains
FED_BACK = 0.5            # a command line is fed back when F V leaves less than this share of it


@dataclass(frozen=True)
class Feedback:
    """The command against the residual's past (module docstring)."""

    closed: bool                 # the command follows past measurements (at level ALPHA, share R2_MIN)
    F: float                     # the F statistic
    p_value: float
    r2: float                    # share of what the command's own past leaves that v's past explains
    coef: np.ndarray             # (m, LAGS, p): u_i,k += sum_l coef[i, l - 1, j] v_j,k-l
    Ts: float

    def response(self, f_hz: float) -> np.ndarray:
        """F(f) (m, p): the FIR's frequency response, sum_l coef_l e^{-i 2 pi f l Ts}."""
        lag = np.arange(1, self.coef.shape[1] + 1)
        z = np.exp(-2j * np.pi * f_hz * self.Ts * lag)
        return np.einsum("ilj,l->ij", self.coef, z)

    def sentence(self) -> str:
        return (f"the record looks closed-loop: the command follows past measurements (F = {self.F:.3g}, "
                f"p = {self.p_value:.2g}; the residual's past explains {100 * self.r2:.3g} % of what the command's "
                "own past leaves of it). The residual y - G u of the recorded command is still the noise, so the "
                "fit stands; a line the controller copied from the measurement into the command is taken for "
                "a sensor effect, not for the mean response's error")


def _sinusoids(x: np.ndarray, freqs, Ts: float) -> tuple[np.ndarray, np.ndarray]:
    """x with its least-squares sinusoids at ``freqs`` (Hz) and its mean removed, and their complex
    amplitudes (len(freqs), columns): a + i b for a cos + b sin."""
    n = x.shape[0]
    k = np.arange(n)
    cols = [np.ones(n)]
    for f in freqs:
        w = 2 * np.pi * f * Ts
        cols += [np.cos(w * k), np.sin(w * k)]
    X = np.column_stack(cols)
    coef, *_ = np.linalg.lstsq(X, x, rcond=None)
    amp = coef[1::2] + 1j * coef[2::2] if len(freqs) else np.zeros((0, x.shape[1]), complex)
    return x - X @ coef, amp


def feedback(u: np.ndarray, v: np.ndarray, Ts: float, lines=(), lags: int = LAGS) -> Feedback | None:
    """The test and the FIR of the module docstring for the command ``u`` (N, m) and the residual
    ``v`` (N, p), the command's lines ``lines`` (Hz) taken out of both first; None when the record
    is too short for the regression or the command has no broadband part (a pure sine)."""
    n = u.shape[0]
    if n < 20 * lags:
        return None
    ub, _ = _sinusoids(u, lines, Ts)
    vb, _ = _sinusoids(v, lines, Ts)
    p, m = v.shape[1], u.shape[1]
    Xv = np.column_stack([vb[lags - l:n - l, j] for l in range(1, lags + 1) for j in range(p)])
    Xu = np.column_stack([ub[lags - l:n - l, i] for l in range(1, lags + 1) for i in range(m)])
    Xv, Xu = Xv - Xv.mean(axis=0), Xu - Xu.mean(axis=0)
    Y = ub[lags:] - ub[lags:].mean(axis=0)
    total = np.sum(Y**2, axis=0)
    if not np.all(total > 1e-24 * max(float(np.sum(u**2)), 1e-300)):
        return None                                    # nothing but the lines: a deterministic command
    # restricted: the command's own past (a PRBS held over bits, a filtered command: the mean
    # response's error in v is a function of past commands, which these carry); full: and v's past
    c_u, *_ = np.linalg.lstsq(Xu, Y, rcond=None)
    rss0 = np.sum((Y - Xu @ c_u) ** 2, axis=0)
    X = np.hstack([Xv, Xu])
    coef, *_ = np.linalg.lstsq(X, Y, rcond=None)
    rss = np.sum((Y - X @ coef) ** 2, axis=0)
    k, dof = Xv.shape[1], Y.shape[0] - X.shape[1] - 1
    Fs = ((rss0 - rss) / k) / np.maximum(rss / dof, 1e-300)
    i = int(np.argmax(Fs))
    pval = float(stats.f.sf(Fs[i], k, dof)) * m                      # Bonferroni over the inputs
    r2 = float(1.0 - rss[i] / max(rss0[i], 1e-300))   # partial: of what the command's own past leaves
    # F's FIR: the command on v's past alone (the response F = -S K from v to u, own lags not
    # separated out), coef (lags * p, m) in the order (lag, output): to (m, lags, p)
    c_v, *_ = np.linalg.lstsq(Xv, Y, rcond=None)
    return Feedback(pval < ALPHA and r2 >= R2_MIN, float(Fs[i]), min(pval, 1.0), r2, c_v.T.reshape(m, lags, p), Ts)


def fed_back_lines(fb: Feedback, u: np.ndarray, v: np.ndarray, lines) -> np.ndarray:
    """The command's lines (Hz) that the controller copied from the residual (module docstring)."""
    if not len(lines):
        return np.zeros(0)
    _, U = _sinusoids(u, lines, fb.Ts)                  # (L, m)
    _, V = _sinusoids(v, lines, fb.Ts)                  # (L, p)
    out = []
    for f, Uf, Vf in zip(lines, U, V):
        # x_k = Re(X e^{-i w k}) for the amplitudes X = a + i b of a cos + b sin, so a FIR
        # u_k = sum_l c_l v_{k-l} maps V to conj(F(f)) V
        pred = np.conj(fb.response(float(f))) @ Vf      # (m,)
        if np.linalg.norm(Uf - pred) < FED_BACK * np.linalg.norm(Uf):
            out.append(float(f))
    return np.array(out)


def mark_closed_loop(S, model, data, say) -> None:
    """Whether the record is under feedback (the command follows the residual's past,
    :func:`feedback`, on the nominal model's residual) and which command lines the controller
    copied from the measurement (:func:`fed_back_lines`): set on ``data`` (a
    :class:`.data.Data`), said in its notes and to ``say``."""
    if not data.has_command:
        return
    k0 = data.k0
    u = data.u[k0:]
    v = S.H.ev.residual(model, False)[0][k0:]
    lines = data.command_lines()
    fb = feedback(u, v, data.Ts, lines)
    if fb is None or not fb.closed:
        return
    data.feedback = fb
    data.fed_back = fed_back_lines(fb, u, v, lines)
    data.notes.append(fb.sentence() + (f" (lines copied: {', '.join(f'{f:.4g}' for f in data.fed_back)} Hz)"
                                       if data.fed_back.size else ""))
    say(data.notes[-1])


def scale_factor_reach(S, cur, data) -> float | None:
    """The smallest sensor gain error |e| (the catalogue's ``gain_start`` effect: a scale factor)
    the diagnosis would add to the fitted model ``cur`` (a :class:`.hypotheses.Fit`) on this
    closed-loop record (module docstring); None for an open-loop record, a model without a plant or
    with that effect already, or no information at all."""
    from ..model.effects import CATALOGUE
    from .thresholds import THRESHOLD

    model = cur.model
    gain = next((eid for eid, cls in CATALOGUE.items() if cls.gain_start), None)
    if data.feedback is None or gain is None or not model.has_plant or gain in model.effects \
            or not model.can_have(gain):
        return None
    name = CATALOGUE[gain].fit.shape[0][0]
    trials = [model] + [model.with_params(gain, {name: e}) for e in (REACH_H, -REACH_H)]
    # the likelihood a candidate is scored by (Search.score): without the level term, which only
    # places a mean effect's parameter (a PI-D's integral holds y at a step's level: there the
    # level's information on e is large and does not count)
    l0, lp, lm = (f.loglik for f in S._map(lambda m: S.H.inner_fit(m, cur.free), trials))
    info = -(lp + lm - 2.0 * l0) / REACH_H**2
    if not info > 0:
        return None
    return float(np.sqrt((THRESHOLD + np.log(data.n_bic)) / info))


def reach_sentence(reach: float) -> str:
    """The note on :func:`scale_factor_reach`."""
    return ("under feedback a sensor's scale factor shows through what the reference puts into the command: "
            f"on this record one of about {100 * reach:.2g} % or more would be found (the fitted model's "
            "information on it); a larger or richer reference lowers that")
