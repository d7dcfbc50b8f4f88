"""95 % profile-likelihood intervals of the fitted parameters (2 Delta l = 3.84, Wilks 1938).

Each parameter is profiled (the others re-optimized at each value) as an independent task
(:func:`interval_tasks`), one per output for a parameter fitted per output. The jitter's interval
is adjusted by its sandwich (Godambe) variance (:func:`.sandwich.godambe_factor`): its Whittle
part takes a modulated noise as stationary and its modulation term reads the same squared
residuals, so the plain likelihood overstates what they say about std_s (about 2x in variance
under a sine command).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ..model import ModelError
from ..model.effects import CATALOGUE
from ..model.filter_cascade import line_gain
from .edits import (
    PER_CHANNEL,
    _scale_name,
    _scale_ref,
    _set,
    _set_scale,
    _shape_value,
    _shape_values,
    _unit_scale,
    n_channels,
    shape_channels,
)
from .hypotheses import Fit, Hypotheses
from .inner import _crossing
from .sandwich import _behind_nonlinearity, _scale_chi2
from .thresholds import CHI2_95, UNBOUNDED


# -- intervals ----------------------------------------------------------------------------------------------
class ChannelKey(NamedTuple):
    """An interval task's key (:func:`interval_tasks`) for one output's value of a parameter fitted
    per output: ``side`` 0 or 1 (its lower or upper end, each its own profile search) or None (its
    whole interval); ``ch`` the output, ``n`` how many outputs the parameter has, ``main``: the
    output whose interval is also the parameter's one interval (the largest value's)."""

    name: str
    side: int | None
    ch: int
    n: int
    main: bool


def merge_intervals(done: list) -> tuple[dict, dict]:
    """({name: interval}, {name: [each output's interval or None]}) from :func:`interval_tasks`'
    (key, result) pairs. The second holds the parameters fitted per output (:class:`ChannelKey`);
    the first, every parameter, one of those as its ``main`` output's interval."""
    out: dict = {}
    per: dict = {}
    main: dict = {}
    for key, res in done:
        if key is None:                              # (intervals, per output) of several parameters
            out.update(res[0])
            per.update(res[1])
        elif isinstance(key, ChannelKey):
            ivs = per.setdefault(key.name, [None] * key.n)
            if key.side is None:
                ivs[key.ch] = res
            else:
                if ivs[key.ch] is None:
                    ivs[key.ch] = [None, None]
                ivs[key.ch][key.side] = res
            if key.main:
                main[key.name] = key.ch
        elif isinstance(key, tuple):                 # (name, 0 | 1): one end
            out.setdefault(key[0], [None, None])[key[1]] = res
        else:
            out[key] = res
    for name, j in main.items():
        out[name] = per[name][j]
    return out, per


def per_output(model, eid: str) -> bool:
    """Whether ``eid``'s per-channel values are one per output (a sensor effect of a model of
    several outputs), so that each output's interval is profiled (:func:`interval_tasks`); an
    actuator's or process noise's channels are its inputs, and their interval stays the largest
    channel's."""
    return CATALOGUE[eid].stage == "sensor" and model.p > 1


def interval_tasks(H: Hypotheses, fit: Fit, eid: str, line_hz: float | None = None) -> list:
    """95 % profile-likelihood intervals of ``eid``'s free parameters at the joint fit (every other
    free variance re-optimized, and the effect's own searched parameters too for its variance: a
    Gauss-Markov std and its tau trade off against each other), as independent (key, thunk) pairs
    to run concurrently (:func:`merge_intervals` assembles them). key: a parameter
    name (its interval), (name, 0 or 1) (its lower or upper end: each end is its own profile
    search), a :class:`ChannelKey` (one output's interval or end, for a parameter fitted per output),
    or None (intervals and per-output intervals of several parameters).

    A parameter fitted one value per output (:func:`per_output`: a sensor noise's variance, a
    scale factor's value per output) gets each output's own interval: the profile over that
    output's value alone, every other free value (the other outputs' too) re-optimized at each
    point, as for the one parameter of a single output. Its one interval (the ``name`` key) is the
    output's whose value is the largest, as for a parameter fitted per input.

    ``line_hz``: for an effect of several lines (``repeatable``), the line's frequency whose
    intervals are asked (default: the fitted line's)."""
    eff = fit.model.effects.get(eid)
    if eff is None:
        return []
    spec = CATALOGUE[eid].fit
    p = fit.model.p
    if spec.kind == "line":
        return [(None, lambda: _tone_intervals(H, fit, eid, line_hz))]
    if spec.kind == "grid":
        # found exactly on the data's grid: each output's step is its own interval; the one interval
        # is the range of the outputs' steps
        sname = spec.scale
        step = eff.param_dict()[sname]
        iv = [step, step] if not isinstance(step, list) else [min(step), max(step)]
        own = np.broadcast_to(np.asarray(eff.params[sname], float), (p,))
        per = {sname: [[float(v), float(v)] for v in own]} if isinstance(step, list) else {}
        return [(None, lambda: ({sname: iv}, per))]
    shaped = [sh for sh in spec.shape if sh[0] in fit.free.get(eid, [])]
    out = []
    if eid in fit.scale_ids:
        name, power = _scale_name(eff)
        vals = np.broadcast_to(np.asarray(eff.params[name], float), (n_channels(fit.model, eid),))
        top = int(np.argmax(vals))
        chans = sorted({c for e, c in zip(fit.scale_ids, fit.scale_ch) if e == eid and c is not None})
        each = chans if chans and per_output(fit.model, eid) else [top] if chans else [None]
        for j in each:
            val = float(np.max(vals) if j is None else vals[j])
            if shaped:
                tasks = [(side, lambda side=side, j=j, val=val:
                          _profile_scale_shaped(H, fit, eid, name, val, 2 * side - 1, j)) for side in (0, 1)]
            else:
                tasks = [(None, lambda j=j, val=val: _profile_scale(H, fit, eid, name, power, val, j))]
            for side, task in tasks:
                if len(each) > 1:
                    key = ChannelKey(name, side, j, p, j == top)
                else:
                    key = name if side is None else (name, side)
                out.append((key, task))
    for sh in shaped:
        # one value per channel (:data:`.edits.PER_CHANNEL`): each output's own interval; a per-input
        # one's, the largest channel's (in magnitude), as a noise's of several inputs is
        ch = None
        chans = [None]
        if PER_CHANNEL in fit.free.get(eid, ()) and shape_channels(fit.model, eid) > 1:
            v = _shape_values(eff, sh[0], H.data.Ts)
            ch = int(np.argmax(np.abs(v))) if v is not None and v.size > 1 else None
            chans = list(range(shape_channels(fit.model, eid))) if per_output(fit.model, eid) else [ch]
        for j in chans:
            for side in (0, 1):
                key = ChannelKey(sh[0], side, j, len(chans), j == ch) if len(chans) > 1 else (sh[0], side)
                out.append((key, lambda sh=sh, side=side, j=j: _profile_outer(H, fit, eid, sh, 2 * side - 1, j)))
    return out


def _profile_scale(H: Hypotheses, fit: Fit, eid: str, name: str, power: int, val: float, j: int | None) -> list:
    """The 95 % profile interval of an effect's scale whose variance is one of the inner problem's
    (no searched parameter: :meth:`.inner.Inner.profile`, the other variances re-optimized at each value):
    channel ``j``'s (value ``val``), or (None) the one factor over its channels. The scale is
    ref v^(1 / power) (:meth:`.hypotheses.Hypotheses.inner_fit`), so the variance's ends map to
    val (v_end / v_hat)^(1 / power); at v_hat = 0 (none of it fitted) through the reference."""
    a = fit.scale_ids.index(eid) if j is None else \
        next(i for i, (e, c) in enumerate(zip(fit.scale_ids, fit.scale_ch)) if e == eid and c == j)
    lo, hi = fit.inner.profile(a, fit.v, fit.loglik - _extra(H, fit), _scale_chi2(H, fit, eid, a))
    vhat = float(fit.v[a])
    if vhat > 0 and val > 0:
        return [val * (lo / vhat) ** (1 / power), val * (hi / vhat) ** (1 / power)]
    ref = _scale_ref(eid, name, H.data.Ts)
    return [ref * lo ** (1 / power), ref * hi ** (1 / power)]


WANDER_Z = 3.29          # the halves' frequencies differ by this many sd: the line wanders (two-sided 0.1 %)


def _tone_intervals(H: Hypotheses, fit: Fit, eid: str, line_hz: float | None = None) -> tuple[dict, dict]:
    """Least-squares amplitude (Var = 2 S / N) and the Cramer-Rao bound of the frequency
    (Var(w) = 12 / (eta N^3) with eta = A^2 / (2 S), i.e. 24 S / (A^2 N^3): Kay 1993 eq. 3.41), S
    the residual's per-sample spectral density next to the line (the 40 bins on each side, the
    line's own +-3 bins left out). ({name: interval}, {name: per output}) as
    :func:`merge_intervals` takes them: the amplitude is each output's own (several outputs), the
    one frequency's interval and the amplitude's one interval are the largest amplitude's.

    The bound holds for a line of fixed frequency. A line whose frequency wanders over the record
    (a motor's, a vibration's) is checked across the record's halves: the frequency fitted on each
    half (:func:`.tones.refine_frequency` on the residual with that line left in) differs by more
    than the two halves' own bounds allow (|f1 - f2| > :data:`WANDER_Z` sqrt(s1^2 + s2^2), a
    two-sided 0.1 % test: a steady line is widened once in a thousand records), then the interval
    is widened to cover both halves' estimates with their 95 % bounds: as wide as the data support,
    not the bound of a steady line that is not there.

    ``line_hz``: the line of an effect of several (``repeatable``) nearest this frequency (default:
    the fitted one, ``all_lines()[0]``)."""
    d = H.data
    tone = fit.model.effects[eid]
    aname = CATALOGUE[eid].fit.scale
    lines = tone.all_lines() if type(tone).repeatable else \
        [(np.asarray(tone.params[aname], float), np.asarray(tone.params["frequency_hz"], float))]
    k_line = 0 if line_hz is None else int(np.argmin([abs(float(np.max(f)) - line_hz) for _, f in lines]))
    amp = np.broadcast_to(lines[k_line][0], (d.p,)).astype(float)
    freq = np.broadcast_to(lines[k_line][1], (d.p,)).astype(float)
    # the measurement's amplitude (through the sensor's own filter, |H(f)|) sets the bounds; the
    # amplitude's interval is the parameter's (before the filter)
    gain = line_gain(fit.model, eid, freq)
    r, _, _ = H.ev.residual(fit.model, True)
    with_line = H.ev.residual(_line_zeroed(fit.model, eid, k_line), False)[0]   # the line left in
    n = d.N - d.k0
    lo_a, hi_a, lo_f, hi_f = [], [], [], []
    for j in range(d.p):
        x = r[d.k0:, j] - r[d.k0:, j].mean()
        X = np.abs(np.fft.rfft(x)) ** 2 / n
        b = int(round(freq[j] * n * d.Ts))
        idx = np.r_[max(1, b - 43):max(1, b - 3), b + 4:min(X.size, b + 44)]
        S = float(np.mean(X[idx])) if idx.size else float(np.var(x))
        a_out = amp[j] * gain[j]
        sa = math.sqrt(2 * S / n) / max(gain[j], 1e-300)
        sf = math.sqrt(24 * S / (max(a_out, 1e-300) ** 2 * n**3)) / (2 * np.pi * d.Ts) if a_out > 0 else 0.0
        lo_a.append(max(amp[j] - 1.96 * sa, 0.0))
        hi_a.append(amp[j] + 1.96 * sa)
        f_lo, f_hi = freq[j] - 1.96 * sf, freq[j] + 1.96 * sf
        halves = _half_frequencies(with_line[d.k0:, j], a_out, freq[j], S, d.Ts) if a_out > 0 else None
        if halves is not None:
            (f1, s1), (f2, s2) = halves
            if abs(f1 - f2) > WANDER_Z * math.hypot(s1, s2):
                f_lo = min(f_lo, f1 - 1.96 * s1, f2 - 1.96 * s2)
                f_hi = max(f_hi, f1 + 1.96 * s1, f2 + 1.96 * s2)
        lo_f.append(f_lo)
        hi_f.append(f_hi)
    k = int(np.argmax(amp))
    per = {aname: [[a, b] for a, b in zip(lo_a, hi_a)]} if d.p > 1 else {}
    return {aname: [lo_a[k], hi_a[k]], "frequency_hz": [lo_f[k], hi_f[k]]}, per


def line_halves(H: Hypotheses, model, eid: str, k_line: int) -> list:
    """Per output: [(frequency, sd) of each half] of line ``k_line`` of effect ``eid``
    (:func:`_half_frequencies`), or None where a half is too short to resolve it."""
    d = H.data
    eff = model.effects[eid]
    amp, freq = (np.broadcast_to(v, (d.p,)).astype(float) for v in eff.all_lines()[k_line])
    amp = amp * line_gain(model, eid, freq)           # in the measurement (through the sensor's filter)
    r = H.ev.residual(model, False)[0]
    full = H.ev.residual(_line_zeroed(model, eid, k_line), False)[0]
    out = []
    for j in range(d.p):
        x = r[d.k0:, j] - r[d.k0:, j].mean()
        n = x.size
        X = np.abs(np.fft.rfft(x)) ** 2 / n
        b = int(round(freq[j] * n * d.Ts))
        idx = np.r_[max(1, b - 43):max(1, b - 3), b + 4:min(X.size, b + 44)]
        S = float(np.mean(X[idx])) if idx.size else float(np.var(x))
        out.append(_half_frequencies(full[d.k0:, j], amp[j], freq[j], S, d.Ts) if amp[j] > 0 else None)
    return out


def _line_zeroed(model, eid: str, k_line: int):
    """``model`` with line ``k_line`` of effect ``eid`` at amplitude 0: its residual keeps that line
    (the others removed)."""
    eff = model.effects[eid]
    aname = CATALOGUE[eid].fit.scale
    params = eff.param_dict()
    if k_line == 0:
        params[aname] = 0.0
    else:
        params["lines"] = [dict(ln, **{aname: 0.0}) if i == k_line - 1 else ln for i, ln in enumerate(params["lines"])]
    return model.with_params(eid, params)


def _half_frequencies(full: np.ndarray, amp: float, freq: float, S: float, Ts: float):
    """[(frequency, its Cramer-Rao sd)] of the line (amplitude ``amp`` at ``freq`` Hz) fitted on
    each half of ``full`` (the residual with the line in it), S the per-sample density next to it;
    None when a half is too short to resolve the line (fewer than 8 of its cycles)."""
    from .tones import refine_frequency
    n = full.size
    h = n // 2
    if h * Ts * freq < 8:
        return None
    out = []
    for seg in (full[:h], full[h:2 * h]):
        f = refine_frequency(seg, freq, Ts, 0, 3.0 / (h * Ts))      # within +-3 of the half's bins
        s = math.sqrt(24 * S / (max(amp, 1e-300) ** 2 * h**3)) / (2 * np.pi * Ts)
        out.append((f, s))
    return out

def _profile_scale_shaped(H: Hypotheses, fit: Fit, eid: str, name: str, val: float, direction: int,
                          j: int | None = None) -> float:
    """The lower (``direction`` -1) or upper (+1) end of the profile interval of an effect's scale
    (value ``val``), its searched parameters refitted at every value. A scale per channel
    (:func:`.edits.n_channels`): channel ``j``'s alone, the other channels' variances re-optimized with the
    searched parameters (their data counted as evidence on them); ``j`` None: the one factor over
    the channels (the others scaled along with it)."""
    free = dict(fit.free)
    nc = n_channels(fit.model, eid)
    vec = np.broadcast_to(np.asarray(fit.model.effects[eid].params[name], float), (nc,)).copy()
    per_channel = j is not None
    chi2 = CHI2_95
    if _behind_nonlinearity(fit.model, eid):
        # the variance's sandwich factor where its gain switches (the shape held), for the
        # profile over the shape too
        pairs = list(zip(fit.scale_ids, fit.scale_ch))
        a = pairs.index((eid, j)) if per_channel and (eid, j) in pairs else fit.scale_ids.index(eid)
        chi2 = _scale_chi2(H, fit, eid, a)
    target = fit.loglik - chi2 / 2
    # the others' variances stay free (re-optimized at every value), channel j's is held
    free[eid] = list(fit.free[eid]) + [f"hold:{j}"] if per_channel else [n for n in fit.free[eid] if n != name]

    def at(v):
        if not per_channel:
            return _set_scale(fit.model, eid, name, v, fit.model)
        w = vec.copy()
        w[j] = v
        return _set(fit.model, eid, {name: [float(x) for x in w]})

    def l_at(v):
        try:
            return H.fit(at(v), free, rounds=1).loglik
        except (ModelError, ValueError, np.linalg.LinAlgError):
            return -1e300

    def edge(direction):
        inside, l_in, factor, ref = val, fit.loglik, 1.05, val
        if not val > 0:
            # fitted at 0 (the data have none of it): the lower end is 0; the upper is searched from
            # the value a new effect starts at, first down by decades to a value inside the interval
            if direction < 0:
                return 0.0
            ref = inside = _unit_scale(CATALOGUE[eid].fit, H.data.Ts) * 1e-3
            for _ in range(8):
                l_in = l_at(inside)
                if l_in >= target:
                    break
                inside /= 10.0
            else:
                return inside            # below 1e-8 of that: 0 for any purpose
        outside = inside * factor ** direction
        for _ in range(30):
            l_out = l_at(outside)
            if l_out < target:
                break
            if not UNBOUNDED < outside / ref < 1.0 / UNBOUNDED:
                # the data do not bound it on this side (a channel they hardly see): 0, or the
                # largest value tried (the factor squared at every step overflowed a float)
                return 0.0 if direction < 0 else outside
            inside, l_in, factor = outside, l_out, factor ** 2
            outside = inside * factor ** direction
        else:
            return outside
        return _crossing(l_at, inside, l_in, outside, l_out, target, peak=val if val > 0 else None)

    return edge(direction)


def _extra(H: Hypotheses, fit: Fit) -> float:
    """The parts of the log-likelihood outside the inner problem (grid, fixed jitter)."""
    lin = fit.inner.value(fit.v)[0] if fit.inner is not None else 0.0
    return fit.loglik - lin


def _profile_outer(H: Hypotheses, fit: Fit, eid: str, spec, direction: int, ch: int | None = None) -> float:
    """The lower (``direction`` -1) or upper (+1) end of a searched parameter's profile interval
    (channel ``ch``'s, for a parameter fitted per channel: the other channels re-fitted at each
    value)."""
    name = spec[0]
    lo_b, hi_b, spacing = H._bounds(spec, ch)
    x = _shape_value(fit.model.effects[eid], name, H.data.Ts, ch)
    mean = CATALOGUE[eid].fit.kind == "mean"
    target = fit.objective(mean) - CHI2_95 / 2

    tr = math.log if spacing == "log" else (lambda z: z)

    def l_at(v):
        f = H._try(fit, eid, name, v, ch)
        if f is not None and ch is not None:
            # a profile: the other channels re-fitted (they trade off through shared outputs). The
            # bracket is twice this channel's displacement (it moves when the best is at its
            # end): a bracket of 1/40 of the range with 6 golden steps left the others where they
            # were, a conditional interval; a scale factor of 0.1 on one output and -0.05 on a
            # second, whose noise is coherent with the first's, read 0.0992 in (0.09913, 0.09930)
            # when its spread over records is 0.00056
            dx = max(abs(tr(v) - tr(x)), 1e-9 * max(abs(tr(x)), 1.0))
            for o in range(shape_channels(fit.model, eid)):
                if o != ch:
                    f = H._search(f, eid, spec, coarse=False, n_golden=12, ch=o, step=2.0 * dx)
        return -1e300 if f is None else f.objective(mean)

    def edge(direction):
        inside, l_in, l_out = x, fit.objective(mean), None
        if spacing == "log":
            step = 1.1
            outside = x * step ** direction
            for _ in range(40):
                if outside <= lo_b * 0.5 or outside >= hi_b * 2:
                    l_out = None
                    break
                l_out = l_at(outside)
                if l_out < target:
                    break
                inside, l_in, outside = outside, l_out, outside * (step ** direction)
                step = step ** 1.5
        else:
            span = (hi_b - lo_b) / 200
            outside = x + direction * span
            for _ in range(40):
                l_out = l_at(outside)
                if l_out < target:
                    break
                inside, l_in, outside = outside, l_out, outside + direction * span
                span *= 1.6
        if l_out is not None and -1e299 < l_out < target <= l_in:
            # a bracket of two fitted values: regula falsi on the squared distance from the estimate
            # (3-4 fits where the bisection took 12 to the same 0.02 in log-likelihood)
            return _crossing(l_at, inside, l_in, outside, l_out, target, log=spacing == "log", peak=x)
        for _ in range(12):
            # beyond the searched range, or a value that is no model (an unstable plant): bisection
            mid = math.sqrt(inside * outside) if spacing == "log" else 0.5 * (inside + outside)
            if l_at(mid) > target:
                inside = mid
            else:
                outside = mid
        return 0.5 * (inside + outside)

    return edge(direction)
