"""``sensor.tone``: periodic interference, a sum of lines amplitude_i sin(2 pi f_i t_k + phi_i)
(mains hum and its harmonics, vibration from motors, fans and pumps).

Each line's phase phi_i is random (uniform, one per line and output, drawn once per run), so the
lines are a stationary process: variance sum_i amplitude_i^2 / 2, autocovariance
sum_i (amplitude_i^2 / 2) cos(2 pi f_i tau), a line at each f_i.

Model file: ``amplitude`` and ``frequency_hz`` (one value, or one per output) are a line; further
lines go in ``lines``, a list of tables with the same two keys::

    [sensor.tone]
    amplitude = 1.3e-4
    frequency_hz = 38.0
    lines = [{amplitude = 7.3e-5, frequency_hz = 31.0}, {amplitude = 2e-5, frequency_hz = 76.0}]

The diagnosis finds the lines one after another (:meth:`push_line`): a line found beside those the
model holds becomes ``amplitude`` / ``frequency_hz``, the lines it had move to ``lines``.
"""

from __future__ import annotations

import numpy as np

from ..schema import Table, nonnegative
from .base import Effect, FitSpec, _g, _plain_value

LINES = "lines"
MAX_LINES = 64             # lines one effect holds at most (a bound on a file's size, not on physics)


class SensorTone(Effect):
    id = "sensor.tone"
    stage = "sensor"
    chain_order = 10
    summary = "periodic interference (a tone)"
    fit = FitSpec("line", scale="amplitude")
    repeatable = True

    @classmethod
    def explain(cls, params, Ts, ctx=None):
        return (f"a narrow spectral line at {_g(params['frequency_hz'])} Hz that no noise source explains: "
                f"periodic interference (a tone) of amplitude {_g(params['amplitude'])}")

    def parse(self, t):
        self.params["amplitude"], self.params["frequency_hz"] = self._line(t)
        self.lines: list[tuple[np.ndarray, np.ndarray]] = []
        if t.has(LINES):
            t._absent(LINES, None)
            raw = t.data[LINES]
            if not isinstance(raw, list) or len(raw) > MAX_LINES:
                raise t.error(LINES, f"expected a list of at most {MAX_LINES} tables {{amplitude = ..., "
                                     f"frequency_hz = ...}}, got {type(raw).__name__}"
                                     + (f" of {len(raw)}" if isinstance(raw, list) else ""))
            for i, item in enumerate(raw):
                sub = Table(item, f"{t.path}.{LINES}[{i}]", t.source)
                self.lines.append(self._line(sub))
                sub.done()

    def _line(self, t):
        amp = t.vector("amplitude", self.dims.p, check=nonnegative, expect="amplitudes >= 0")
        nyq = 0.5 / self.dims.Ts
        freq = t.vector("frequency_hz", self.dims.p, check=lambda v: bool(np.all((v > 0) & (v < nyq))),
                        expect=f"frequencies in Hz between 0 and the Nyquist frequency {nyq:g}")
        return amp, freq

    def param_dict(self) -> dict:
        out = {k: _plain_value(v) for k, v in self.params.items()}
        if self.lines:
            out[LINES] = [{"amplitude": _plain_value(a), "frequency_hz": _plain_value(f)} for a, f in self.lines]
        return out

    # -- the lines, for the diagnosis (hooks of :mod:`.base`) ---------------------------------------
    def all_lines(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Every line as (amplitude, frequency_hz), per output: ``amplitude`` / ``frequency_hz``
        first, then ``lines`` in order."""
        return [(np.asarray(self.params["amplitude"], float), np.asarray(self.params["frequency_hz"], float))] \
            + list(self.lines)

    def push_line(self) -> dict:
        """The parameters with the line ``amplitude`` / ``frequency_hz`` moved to the end of
        ``lines`` (the caller sets the new line in its place)."""
        out = self.param_dict()
        out[LINES] = out.get(LINES, []) + [{"amplitude": out.pop("amplitude"),
                                            "frequency_hz": out.pop("frequency_hz")}]
        return out

    def pop_line(self) -> dict:
        """The parameters before :meth:`push_line`: the last of ``lines`` back as the line."""
        out = self.param_dict()
        rest = list(out.pop(LINES))
        last = rest.pop()
        out.update(last)
        if rest:
            out[LINES] = rest
        return out

    # -- simulation ---------------------------------------------------------------------------------
    def init_state(self, static_rng, trials):
        phase = [static_rng.uniform(0.0, 2.0 * np.pi, (trials, self.dims.p))]
        phase += [static_rng.uniform(0.0, 2.0 * np.pi, (trials, self.dims.p)) for _ in self.lines]
        return {"phase": phase, "k": 0}

    def _tone(self, k0, n, state):
        t = np.arange(k0, k0 + n, dtype=np.float64) * self.dims.Ts
        out = 0.0
        for (amp, freq), ph in zip(self.all_lines(), state["phase"]):
            out = out + amp * np.sin(2.0 * np.pi * t[None, :, None] * freq + ph[:, None, :])
        return out

    def sensor_terms(self, e, state, n):
        out = self._tone(state["k"], n, state)
        state["k"] += n
        return out

    def spectral(self):
        return [("tone", amp, freq) for amp, freq in self.all_lines()]
