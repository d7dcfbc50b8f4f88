"""Hypotheses and their fits: a model plus the set of its parameters that are free.

The parameters of the user's model stay at the user's values unless a candidate frees them
(``refit``: the effect is there but a value is wrong). A hypothesis is scored by the likelihood
of :mod:`.evaluator`. How each effect is fitted is declared by the effect itself (``Effect.fit``,
:class:`noiselab.model.effects.base.FitSpec`):

* ``noise`` sources (white, AR(1), Gauss-Markov, bias walk, process noise): the expected
  periodogram is linear in each source's variance, so the variances are fitted together
  (:class:`.inner.Inner`; the profile over the shape parameters, e.g. a correlation time, by a
  grid then golden-section search);
* ``mean`` effects (scale factor, lag, saturation, dead zone) change the predicted response to the
  recorded command: the residual is recomputed for each value of their parameter;
* ``line`` (tone): a deterministic sinusoid in a record; peaks of I_f / E_f beyond what the
  exponential distribution allows over all bins (P < 1e-3) that also stand out from the data's
  spectrum around them (:func:`.tones.tone_peaks`) are candidates (except at a line of the
  recorded command or one of its first :data:`.thresholds.HARMONICS` harmonics: the mean
  response's error), the frequency refined by maximizing the periodogram, amplitude and phase by
  least squares; 3 parameters;
* ``grid`` (quantization): every value on a grid of step Delta. Under any continuous model the
  chance that a value falls within 1e-6 Delta of a grid point is 2e-6, so l_grid = n ln(1/2e-6);
* ``modulated`` (jitter): its power is white on average, like sensor noise, but follows the
  square of the slope (:class:`.modulation.Modulation`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..memo import Memo
from ..model import ModelError
from ..model.effects import CATALOGUE, of_kind
from ..model.predict import mean_key as _mean_key
from . import whittle as W
from .data import Data
from .edits import (
    COMMON,
    PER_CHANNEL,
    _channel,
    _radius,
    _scale_name,
    _scale_ref,
    _set,
    _set_scales,
    _shape_value,
    _shape_values,
    _vec,
    n_channels,
    per_input,
    plant_stable,
    shape_channels,
)
from .evaluator import Evaluator
from .inner import Inner
from .modulation import Modulation
from .thresholds import (
    CHI2_95,
    GRID_TOL,
    MAX_SHIFTS,
    MORE_ROUNDS,
    QUANT_ROUNDS,
    QUANT_SLOPE_MAX,
)
from .tones import refine_frequency


def _stein(parts: dict, mo, keep=()) -> dict:
    """The expected periodogram's parts with a quantizer's covariance with the noise (Stein's
    lemma: Cov(n_j, e_k) = Cov(n_j, x_k) h_k, :mod:`noiselab.model.effects.sensor_quantization`)
    carried by the noise parts: output j's times 1 + 2 h_j, a cross term between outputs j and k
    times sqrt((1 + 2 h_j)(1 + 2 h_k)) (1 + h_j + h_k to first order; this form keeps the
    cross-spectral matrices positive definite). For several outputs only: with one, the term is in
    the quantizer's part, as in the views (negative where the quantizer holds the measurement; the
    likelihood floors the total), which a matrix's determinant cannot take. h <= -1/2 (a mean
    parked on a level) takes the noise out. ``keep``: the parts left as they are (the quantizer's
    own, the tones'). ``mo`` None: the parts as they are."""
    if mo is None:
        return parts
    a = np.sqrt(np.maximum(1.0 + 2.0 * np.asarray(mo.h, float), 0.0))
    if np.all(a == 1.0):
        return parts
    out = {}
    for k, v in parts.items():
        if k in keep:
            out[k] = v
        elif v.ndim == 3:
            out[k] = v * np.outer(a, a)[None]
        else:
            out[k] = v * (a * a)
    return out


def _scales(model, free: dict) -> list:
    """The free variances of a fit: (effect id, parameter, power of the variance, channel or None).
    A sensor noise of several outputs has one variance per output, an actuator or process noise of
    several inputs one per input (:func:`.edits.n_channels`), the others one over their channels;
    "hold:j" among an effect's free names holds channel j's at the model's value (a profile), and
    :data:`.edits.COMMON` makes one factor over the channels."""
    scales = []
    for e, names in free.items():
        if CATALOGUE[e].fit.kind in ("noise", "modulated") and e in model.effects:
            sname, power = _scale_name(model.effects[e])
            if sname in names:
                nc = n_channels(model, e)
                chans = [j for j in range(nc) if f"hold:{j}" not in names] if nc > 1 and COMMON not in names \
                    else (None,)
                scales += [(e, sname, power, j) for j in chans]
    return scales


def _scale_refs(model, scales: list, Ts: float) -> tuple[list, list]:
    """Each scale's current value (its largest channel's, or the channel's) and its reference: where
    the inner problem's variance is 1 (:func:`.edits._scale_ref`; its value under a nonlinearity)."""
    nonlin = any(hasattr(e, "knots") for e in model.effects.values())
    cur, refs = [], []
    for e, sname, _power, j in scales:
        vals = np.atleast_1d(np.asarray(model.effects[e].params[sname], float))
        val = float(np.max(vals) if j is None else np.broadcast_to(vals, (n_channels(model, e),))[j])
        cur.append(val)
        refs.append(val if (nonlin and val > 0) else _scale_ref(e, sname, Ts))
    return cur, refs


def _scale_of(model, eid: str):
    """Effect ``eid``'s scale parameter in ``model`` (``fit.scale``: a grid's step, a jitter's std_s)."""
    return model.effects[eid].params[CATALOGUE[eid].fit.scale]


def _g_moved(a, b, rtol: float = 1e-2) -> bool:
    """Whether two quantizer moments' conditional means differ by more than ``rtol`` of the
    measurement's rms (None: no mean). What it lets pass moves the likelihood by up to about
    N rtol^2 / 2 (N samples), where the residual's rms is the measurement's: an approximation the
    inner fit's rounds accept for their cost (each refresh is a new periodogram)."""
    if a is None or b is None:
        return (a is None) != (b is None)
    scale = np.sqrt(np.mean(b.var_y, axis=0))
    return bool(np.any(np.max(np.abs(a.g - b.g), axis=0) > rtol * scale))


@dataclass
class Fit:
    model: object
    free: dict                      # eid -> list of free parameter names
    loglik: float
    parts: dict = field(default_factory=dict)
    inner: object = None
    v: np.ndarray = None
    scale_ids: list = field(default_factory=list)   # the effect of each of ``v``'s variances
    scale_ch: list = field(default_factory=list)    # ... and its channel (None: all its channels)
    chparts: dict = field(default_factory=dict)     # (effect id, input): that input's part (:func:`.edits.per_input`)
    level_fn: object = None         # () -> l_level (:meth:`.evaluator.Evaluator.level_term`), outside ``loglik``
    _level: float | None = None

    @property
    def level(self) -> float:
        """l_level, computed when first asked for (only a mean effect's search asks)."""
        if self._level is None:
            self._level = float(self.level_fn()) if self.level_fn is not None else 0.0
        return self._level

    def objective(self, mean: bool) -> float:
        """What a search over a parameter maximizes: ``loglik``, plus ``level`` for a mean
        effect's parameter (:meth:`Hypotheses._search`)."""
        return self.loglik + self.level if mean else self.loglik

    def scaled_parts(self) -> dict:
        """{effect id: its part of the expected periodogram at the fitted values}: ``parts`` are at
        the scaling references, each free variance's part (one output's, for a per-output one)
        times its fitted factor."""
        out = {k: E for k, E in self.parts.items() if k not in self.scale_ids}
        for e, j, vi in zip(self.scale_ids, self.scale_ch or [None] * len(self.scale_ids), np.atleast_1d(self.v)):
            if e in self.parts:
                out[e] = out.get(e, 0.0) + _channel(self.parts[e], j, self.chparts, e) * vi
        return out


class Hypotheses:
    def __init__(self, data: Data, base_model):
        self.data = data
        self.ev = Evaluator(data)
        self.base = base_model
        self._qslope = Memo(5, flush=True)
        if data.ramps is None:
            # the ramps' whitener: from the first model's residual (the nominal), one per record
            data.ramps = False
            data.stable = plant_stable(base_model)
            if data.M >= W.RAMP_MIN:
                r = self.ev.residual(base_model, False)[0]
                data.ramps = W.Ramps(np.diff(r[data.k0:], axis=0), data.at_rest)

    def _quant_slope(self, model) -> np.ndarray | None:
        """The part of E[(e_{q+1} - e_q)^2] of a quantizer's error that changes with the mean's step
        dmu_q = mu_{q+1} - mu_q between samples (M, p) (:class:`.modulation.Modulation`'s ``base``); None
        without a quantizer or where it does not matter. For Gaussian noise before the quantizer
        with Var(n_{q+1} - n_q) = V_d, from the error's Fourier series e(x) = sum_n (step / (pi n))
        (-1)^(n+1) sin(2 pi n x / step) (Widrow & Kollar 2008 ch. 4; the terms damped by the noise's
        whole variance, and the error's covariance with the noise, left out), -2 Cov(e_{q+1}, e_q):

            w_q = -(step^2 / pi^2) sum_n n^-2 exp(-2 pi^2 n^2 V_d,q / step^2) cos(2 pi n dmu_q / step)

        (up to a constant, which the regression's intercept takes). A jitter's increments are part
        of V_d,q and follow the slope; the inner fit recomputes this at its fitted values.

        It matters when the noise changes by less than a step between samples (V_d < ~0.35 step^2).
        The terms left out are damped by the noise's whole variance V: exact enough for V above
        ~0.35 step^2 (0.6 step of noise); below, where the conditional mean is in the residual,
        approximate (they follow where the mean sits between the levels). Tones are left out."""
        qid = of_kind(model.effects, "grid")
        if qid is None:
            return None
        d = self.data
        pr = model.predictor()
        st = pr.steady_state()
        gam = pr.variogram(2, quantization=False)
        if any(v is None for v in gam.values()):
            return None
        jid = of_kind(model.effects, "modulated")
        std_s = float(_scale_of(model, jid)) if jid is not None else 0.0
        # the noise's own increments; a jitter's follow the slope: std_s^2 (ydot_{q+1}^2 + ydot_q^2
        # + 2 Var(ydot)) at sample q
        Vd0 = 2.0 * pr.before_quantizer({e: v for e, v in gam.items() if e != jid})[1]   # (p,)
        step = np.broadcast_to(np.asarray(_scale_of(model, qid), float), (d.p,))
        a0 = 2.0 * np.pi**2 * Vd0 / step**2
        if np.all(a0 > QUANT_SLOPE_MAX):
            return None
        key = (_mean_key(model), tuple(float(f"{v:.4g}") for v in a0), tuple(step.tolist()), f"{std_s:.4g}")

        def compute():
            mean, ydot = self.ev.mean(model)
            dmu = np.diff(mean[d.k0:], axis=0)                       # (M, p)
            w = np.zeros_like(dmu)
            if std_s > 0:
                yv = np.zeros(d.p) if st.ydot_var is None else np.broadcast_to(st.ydot_var, (d.p,))
                jv = std_s**2 * (Modulation.slope_squares(ydot, d.k0) + 2.0 * yv)          # (M, p)
            for j in np.flatnonzero(a0 <= QUANT_SLOPE_MAX):
                a = a0[j] if std_s == 0 else a0[j] + 2.0 * np.pi**2 * jv[:, j] / step[j] ** 2
                for n in range(1, 64):
                    damp = np.exp(-a * n * n)
                    if np.max(damp) < 1e-6:
                        break
                    w[:, j] -= damp / n**2 * np.cos(2.0 * np.pi * n * dmu[:, j] / step[j])
                w[:, j] *= step[j] ** 2 / np.pi**2
            return w
        return self._qslope.get_or_compute(key, compute)

    # one evaluation: outer parameters fixed (in ``model``), the free variances fitted
    def inner_fit(self, model, free: dict) -> Fit:
        d = self.data
        self.ev.evals += 1
        scales = _scales(model, free)
        scale_ids = [e for e, *_ in scales]
        scale_ch = [j for *_, j in scales]
        cur, refs = _scale_refs(model, scales, d.Ts)
        canon = _set_scales(model, scales, refs, model)
        tid = of_kind(free, "line")
        r, ydot, tone_amp, Ig = self.ev.grouped_periodogram(model, tid is not None)
        if tone_amp is not None and tid is not None:
            aname = CATALOGUE[tid].fit.scale
            model = _set(model, tid, {aname: _vec(tone_amp)})
            canon = _set(canon, tid, {aname: _vec(tone_amp)})
        # the jitter's slope power: per output, or (several outputs) the matrix of mean products,
        # weighted by the taper like the periodogram (see :func:`.whittle.slope_power`)
        ydot_sq = self.ev.slope_power(model, ydot)
        parts = self._jitter_part(model, self.ev.parts(canon, ydot_sq), scales, refs, ydot_sq)
        chparts = self._input_parts(canon, model, scales, parts, ydot_sq)
        jid = of_kind(model.effects, "modulated")
        mod = mod_index = None
        dd = np.diff(r[d.k0:], axis=0) if jid is not None else None
        if jid in scale_ids:
            mod_index = scale_ids.index(jid)
            mod = Modulation(dd, ydot, d.k0, refs[mod_index] ** 2, self._quant_slope(model))
        qid = of_kind(model.effects, "grid")
        white_q = parts.get(qid)
        qpart = self.ev.quant_part(model) if qid is not None else None
        if qpart is not None:
            # the quantizer's error is correlated when the signal crosses few steps per sample; how
            # much depends on the other sources' variances: from the model's values, then again
            # from the fitted ones until they settle (the part is not linear in them)
            parts = dict(parts)
            parts[qid] = qpart

        def assemble(parts, m):
            return self._assemble(parts, chparts, m, qid, scale_ids, scale_ch, Ig)
        E0, U = assemble(parts, model)
        inner = Inner(Ig, d.weights / W.taper(d.M)[2], E0, U, mod, mod_index)
        res_model = model                              # the model the residual (Ig) is of
        v0 = np.array([(c / ref) ** pw for c, ref, (_, _, pw, _) in zip(cur, refs, scales)]) if scales else None
        v, l = inner.optimize(v0)

        def values(v):               # the scales' values at the inner problem's variances v
            return [ref * vi ** (1.0 / sc[2]) for sc, vi, ref in zip(scales, v, refs)]

        for _ in range(QUANT_ROUNDS if qid is not None and scales else 0):
            trial = _set_scales(model, scales, values(v), model)
            # the quantizer's slope modulation at the fitted noise and jitter (:meth:`_quant_slope`)
            base_moved = False
            if mod is not None and mod.base is not None:
                nb = self._quant_slope(trial)
                scale = float(np.max(np.abs(mod.base))) or 1.0
                if nb is not None and not np.allclose(nb, mod.base, rtol=1e-2, atol=1e-2 * scale):
                    mod, base_moved = Modulation(dd, ydot, d.k0, refs[mod_index] ** 2, nb), True
            new_q = self.ev.quant_part(trial)
            new_q = white_q if new_q is None else new_q          # white at the fitted values
            # the quantizer's conditional mean, in the residual, follows the noise too
            mo_t, mo_r = self.ev.quant_moments(trial)[0], self.ev.quant_moments(res_model)[0]
            moved = _g_moved(mo_t, mo_r)
            # with the conditional mean, its Stein factors move the part too: settled to 1 %
            if np.allclose(new_q, parts[qid], rtol=1e-3 if mo_t is None else 1e-2, atol=0) and not (moved or base_moved):
                break
            parts = dict(parts)
            parts[qid] = new_q
            if moved:
                res_model = trial
                Ig = self.ev.grouped_periodogram(res_model, tid is not None)[3]
            E0, U = assemble(parts, res_model)
            inner = Inner(Ig, d.weights / W.taper(d.M)[2], E0, U, mod, mod_index)
            v, l = inner.optimize(v)
        if jid is not None and jid not in scale_ids:
            # a fixed jitter still explains (or not) the modulation
            l += Modulation(dd, ydot, d.k0, 1.0, self._quant_slope(model))(float(_scale_of(model, jid)) ** 2)[0]
        if d.grid is not None:
            l += self.grid_loglik(model)
        l += self.ev.ramp_term(res_model, tid is not None)
        fitted = _set_scales(model, scales, values(v), model)
        ev, tone_free = self.ev, tid is not None
        return Fit(fitted, free, l, parts, inner, v, scale_ids, scale_ch, chparts,
                   lambda: ev.level_term(res_model, tone_free, fitted))

    def _jitter_part(self, model, parts: dict, scales: list, refs: list, ydot_sq) -> dict:
        """``parts`` with a ``modulated`` effect's (jitter) part recomputed where other variances are
        free: its power includes the noise-driven slope, std_s^2 Var(ydot), set by the other sources'
        variances: from their current values, not the scaling references of the canonical model
        (a process noise of unit std made the jitter's part 4x too large on a two-output case)."""
        d = self.data
        jid = of_kind(model.effects, "modulated")
        scale_ids = [e for e, *_ in scales]
        if jid is None or not any(e != jid for e in scale_ids):
            return parts
        jm = model if jid not in scale_ids else \
            _set(model, jid, {CATALOGUE[jid].fit.scale: refs[scale_ids.index(jid)]})
        parts = dict(parts)
        parts[jid] = W.expected_parts(
            jm, d.M, d.k0, d.at_rest, ydot_sq=ydot_sq, skip=tuple(e for e in jm.effects if e != jid),
            groups=d.groups, cross=d.p > 1)[jid]
        return parts

    def _input_parts(self, canon, model, scales: list, parts: dict, ydot_sq) -> dict:
        """{(effect id, input j): its part on input j alone} for the scales fitted per input: an
        input's part reaches every output (not a diagonal element), so each input's is computed apart,
        the effect's scale at its value in ``canon`` on that input alone (parts are linear in it)."""
        chparts = {}
        for e, sname in dict.fromkeys((e, sname) for e, sname, _, j in scales if j is not None and per_input(e)):
            vec = np.broadcast_to(np.asarray(canon.effects[e].params[sname], float), (n_channels(model, e),))
            for j in range(vec.size):
                one = np.where(np.arange(vec.size) == j, vec, 0.0)
                chparts[(e, j)] = self.ev.parts(_set(canon, e, {sname: [float(x) for x in one]}), ydot_sq)[e] \
                    if vec[j] > 0 else np.zeros_like(parts[e])
        return chparts

    def _assemble(self, parts: dict, chparts: dict, m, qid, scale_ids: list, scale_ch: list, Ig):
        """E0 and U of :class:`.inner.Inner`: the fixed parts (every effect without a free variance,
        and the channels held of one with a variance per channel, at the model's value) and each free
        variance's part, the noise parts times the quantizer's Stein factors (:func:`_stein`)."""
        mo = self.ev.quant_moments(m)[0] if qid in m.effects and self.data.p > 1 else None
        keep = (qid, *m.predictor().tone_ids()) if mo is not None else ()
        ps, cps = _stein(parts, mo, keep), _stein(chparts, mo, keep)
        pairs = set(zip(scale_ids, scale_ch))
        held = [_channel(ps[e], j, cps, e) for e in {e for e, j in pairs if j is not None} if e in ps
                for j in range(n_channels(m, e)) if (e, j) not in pairs]
        return (sum((v for k, v in ps.items() if k not in scale_ids), np.zeros_like(Ig)) + sum(held, np.zeros_like(Ig)),
                [_channel(ps.get(e, np.zeros_like(Ig)), j, cps, e) for e, j in zip(scale_ids, scale_ch)])

    def grid_loglik(self, model) -> float:
        """l_grid: values on the model's quantization grid (ln(1 / 2e-6) each) when the data are."""
        qid = of_kind(model.effects, "grid")
        if qid is None:
            return 0.0
        step = np.broadcast_to(_scale_of(model, qid), (self.data.p,))
        l = 0.0
        for j, g in enumerate(self.data.grid):
            if g is not None and np.isclose(step[j], g, rtol=1e-6):
                l += self.data.N * math.log(1 / (2 * GRID_TOL))
        return l

    # outer parameters: grid then golden section, coordinate ascent
    def fit(self, model, free: dict, rounds: int = 2, new: tuple = (), screen: bool = False,
            only: tuple | None = None) -> Fit:
        """Fit the free parameters of ``model``. ``new``: effects whose searched parameters get a
        coarse grid over their whole range first (the others start from their current values).
        ``screen``: a cheap pass that searches only the new effects' parameters, once, with a
        coarser grid (candidates are ranked by it, then the leaders are fitted in full).
        ``only``: search only these effects' parameters (the variances are always fitted)."""
        best = self.inner_fit(model, free)
        outer = [(e, spec) for e in free for spec in CATALOGUE[e].fit.shape if spec[0] in free[e]
                 and (not screen or e in new) and (only is None or e in only)]
        # the new effects first, in the order given: a candidate searched jointly with the mean
        # effects already in gets its coarse grid beside their fitted values, before they move
        # (a scale factor started mid-range at +25 % sent a fitted lag along the ridge the two
        # share, and two rounds stopped 120 below the truth in 2 Delta l: generated case 229)
        outer.sort(key=lambda x: new.index(x[0]) if x[0] in new else len(new))
        tid = of_kind(free, "line")
        if tid is not None and "frequency_hz" in free[tid] and (not screen or tid in new):
            best = self._fit_tone_frequency(best, tid)
        n_rounds = 1 if screen else rounds
        rnd = 0
        mean = any(CATALOGUE[e].fit.kind == "mean" for e, _ in outer)
        while rnd < n_rounds:
            before = best.objective(mean)
            x0 = self._coords(best, outer)
            for e, spec in outer:
                best = self._search(best, e, spec, coarse=(rnd == 0 and e in new),
                                    n_grid=7 if screen else 9, n_golden=6 if screen else 10)
            if rnd > 0 or not new:
                best = self._pattern(best, outer, x0)
            gain = best.objective(mean) - before
            if gain < 0.05:
                break
            rnd += 1
            if rnd == n_rounds and not screen and len(outer) > 1 and gain > 1.0 and n_rounds < rounds + MORE_ROUNDS:
                n_rounds += 1           # still climbing a ridge the parameters share: one more round
        # a mean effect's parameter one per channel (:data:`.edits.PER_CHANNEL`): from the common value,
        # each channel's over its whole range, then each around its value, while a round gains
        # (the channels trade off through the outputs they share: a ridge, climbed by more rounds
        # while one still gains more than 1 in l)
        per_ch = [(e, spec) for e, spec in outer if PER_CHANNEL in free[e] and shape_channels(best.model, e) > 1]
        n_rounds = 1 if screen else rounds
        rnd = 0
        while per_ch and rnd < n_rounds:
            before = best.objective(True)
            for e, spec in per_ch:
                for j in range(shape_channels(best.model, e)):
                    best = self._search(best, e, spec, coarse=(rnd == 0 and e in new),
                                        n_grid=7 if screen else 9, n_golden=6 if screen else 10, ch=j)
            gain = best.objective(True) - before
            if gain < 0.05:
                break
            rnd += 1
            if rnd == n_rounds and not screen and gain > 1.0 and n_rounds < rounds + 2 * MORE_ROUNDS:
                n_rounds += 1
        return best

    def _coords(self, fit: Fit, outer) -> np.ndarray:
        """The searched parameters in the search's coordinates (ln for log-spaced ones)."""
        out = []
        for e, spec in outer:
            v = _shape_value(fit.model.effects[e], spec[0], self.data.Ts)
            out.append(np.nan if v is None else (math.log(v) if spec[4] == "log" and v > 0 else float(v)))
        return np.array(out)

    def _pattern(self, fit: Fit, outer, x0: np.ndarray) -> Fit:
        """Hooke-Jeeves pattern moves: after a round of one-parameter searches moved several
        parameters, try continuing along that displacement (1, 2, 4 times it) while it gains. Two
        parameters that trade off (a lag and a scale factor both set the response's amplitude)
        form a ridge that coordinate searches climb in small zigzags."""
        if len(outer) < 2:
            return fit
        x1 = self._coords(fit, outer)
        dx = x1 - x0
        if not np.all(np.isfinite(dx)) or np.count_nonzero(np.abs(dx) > 1e-12) < 2:
            return fit
        best = fit
        mean = all(CATALOGUE[e].fit.kind == "mean" for e, _ in outer)
        for lam in (1.0, 2.0, 4.0):
            x = x1 + lam * dx
            m = fit.model
            try:
                for (e, spec), xi in zip(outer, x):
                    lo, hi, spacing = self._bounds(spec)
                    v = math.exp(xi) if spacing == "log" else float(xi)
                    if not lo <= v <= hi:
                        raise ValueError("outside the parameter's range")
                    m = _set(m, e, {spec[0]: v})
                if _radius(m.Ad) >= 1.0 and _radius(self.base.Ad) < 1.0:
                    break
                f = self.inner_fit(m, fit.free)
            except (ModelError, ValueError, np.linalg.LinAlgError):
                break
            if f.objective(mean) <= best.objective(mean):
                break
            best = f
        return best

    def _bounds(self, spec, ch: int | None = None):
        """A searched parameter's range (channel ``ch``'s: an input's own command for "umax")."""
        name, lo, hi, unit, spacing = spec
        d = self.data
        if unit == "Ts|T":
            return lo * d.Ts, hi * d.T, spacing
        if unit == "fs":                # a frequency, as a fraction of the sample rate
            return lo / d.Ts, hi / d.Ts, spacing
        if unit == "umax":
            um = d.umax if ch is None or ch >= d.umax_in.size or d.umax_in[ch] <= 0 else float(d.umax_in[ch])
            return lo * um, hi * um, spacing
        return lo, hi, spacing

    def _try(self, fit: Fit, e: str, name: str, value: float, ch: int | None = None) -> Fit | None:
        """The fit with ``e``'s ``name`` at ``value`` (at channel ``ch`` alone, the others kept)."""
        try:
            if ch is not None:
                vals = np.broadcast_to(_shape_values(fit.model.effects[e], name, self.data.Ts),
                                       (shape_channels(fit.model, e),)).copy()
                vals[ch] = value
                value = _vec(vals)
            m = _set(fit.model, e, {name: value})
            if _radius(m.Ad) >= 1.0 and _radius(self.base.Ad) < 1.0:
                return None            # e.g. a lag faster than Ts under forward Euler: not a model of anything
            return self.inner_fit(m, fit.free)
        except (ModelError, ValueError, np.linalg.LinAlgError):
            return None

    def _search(self, fit: Fit, e: str, spec, coarse: bool, n_grid: int = 9, n_golden: int = 10,
                ch: int | None = None, step: float | None = None) -> Fit:
        """One searched parameter (all channels alike, or channel ``ch`` alone): a grid over its
        range when ``coarse`` (or unset), then golden section around the best (the bracket's half
        width ``step`` in the search's coordinates, log or linear; default 1/40 of the range)."""
        lo, hi, spacing = self._bounds(spec, ch)
        name = spec[0]
        cur = _shape_value(fit.model.effects[e], name, self.data.Ts, ch)
        tr = (np.log, np.exp) if spacing == "log" else (lambda x: x, lambda x: x)
        a, b = tr[0](lo), tr[0](hi)
        best = fit
        # a mean effect's parameter sets the level a step settles at: the record's level enters
        mean = CATALOGUE[e].fit.kind == "mean"
        if coarse or cur is None:
            xs = np.linspace(a, b, n_grid)
            for x in xs:
                f = self._try(fit, e, name, float(tr[1](x)), ch)
                if f is not None and f.objective(mean) > best.objective(mean):
                    best = f
            step = (b - a) / (n_grid - 1)
        elif step is None:
            step = (b - a) / 40
        c = _shape_value(best.model.effects[e], name, self.data.Ts, ch)
        if c is None:                  # nothing on the grid was valid and the effect has no value yet
            return fit
        gr = (math.sqrt(5) - 1) / 2
        # golden section in [x0 - step, x0 + step]; when the maximum is found at an end of that
        # bracket (not at the parameter's bound), the bracket moves there and the search goes on:
        # a refit after another effect was added can move a correlation time by more than one step
        for _ in range(1 if coarse or cur is None else MAX_SHIFTS + 1):
            x0 = tr[0](c)
            lo2, hi2 = max(a, x0 - step), min(b, x0 + step)
            a2, b2 = lo2, hi2
            cache = {}

            def val(x):
                if x not in cache:
                    cache[x] = self._try(best, e, name, float(tr[1](x)), ch)
                f = cache[x]
                return -1e300 if f is None else f.objective(mean)

            c1, d1 = b2 - gr * (b2 - a2), a2 + gr * (b2 - a2)
            for _ in range(n_golden):
                if val(c1) > val(d1):
                    b2, d1 = d1, c1
                    c1 = b2 - gr * (b2 - a2)
                else:
                    a2, c1 = c1, d1
                    d1 = a2 + gr * (b2 - a2)
            moved = False
            for f in cache.values():
                if f is not None and f.objective(mean) > best.objective(mean):
                    best, moved = f, True
            if not moved:
                break
            c = _shape_value(best.model.effects[e], name, self.data.Ts, ch)
            xb = tr[0](c)
            edge = gr ** n_golden * (hi2 - lo2) * 2
            if not ((xb - lo2 < edge and lo2 > a) or (hi2 - xb < edge and hi2 < b)):
                break
        return best

    def _fit_tone_frequency(self, fit: Fit, tid: str) -> Fit:
        d = self.data
        tone = fit.model.effects[tid]
        freq = np.broadcast_to(tone.params["frequency_hz"], (d.p,)).astype(float).copy()
        ym, _ = self.ev.mean(fit.model)
        mo = self.ev.quant_moments(fit.model)[0]
        r = d.y - ym if mo is None else d.y - ym - mo.g
        for j in range(d.p):
            freq[j] = refine_frequency(r[:, j], freq[j], d.Ts, d.k0, 1.0 / (d.M * d.Ts))
        m = _set(fit.model, tid, {"frequency_hz": _vec(freq)})
        f = self.inner_fit(m, fit.free)
        # the periodogram's peak is the line's maximum-likelihood frequency (Kay 1993 ch. 7); the
        # Whittle likelihood of group means cannot resolve shifts of a CRLB (its differences there are
        # +-0.1, noise), so it only vetoes a refinement it rejects at 5 %: keeping the start on a
        # smaller difference left the frequency on its grid value in a quarter of the records
        return f if f.loglik >= fit.loglik - CHI2_95 / 2 else fit
