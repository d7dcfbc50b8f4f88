"""The likelihood of one hypothesis: its residual and its noise spectrum, evaluated and cached.

Every hypothesis (:mod:`.hypotheses`) is scored by one likelihood:

    l = l_Whittle(residual spectrum | the hypothesis' noise spectrum)      (:mod:`.whittle`)
        + l_grid   (values on a grid: quantization)
        + l_mod    (residual power that follows the slope: jitter, :mod:`.modulation`)
        + l_ramp   (the first and last tenth of the record, which the periodogram's taper weighs
                    down: the mean response there, by whitened least squares; :class:`.whittle.Ramps`)

A record from rest adds l_level (:func:`.whittle.level_loglik`): its residual's mean against the
spread the hypothesis predicts for it. Differencing removes the record's level, and with it what
a step command says about a mean effect (a saturation, a dead zone, a scale factor set the level
the output settles at: under a step the level pins a saturation's limit ~10x more tightly than
the differenced likelihood does). It enters the search over a mean effect's parameter and that
parameter's profile interval (``Fit.objective``), not the comparison between hypotheses: under
slow noise (a walk, a Gauss-Markov bias of long tau) the mean is not independent of the
differenced record, and in the comparison its marginal density took a hidden walk for a
Gauss-Markov bias.
"""

from __future__ import annotations

import math

import numpy as np

from ..memo import Memo
from ..model.effects import of_kind
from ..model.filter_cascade import line_gain, output_filter_of
from ..model.predict import free_response_fit
from ..model.predict import mean_key as _mean_key
from . import whittle as W
from .data import Data, mean_response
from .thresholds import QUANT_LAGS, QUANT_TAIL
from .tones import tone_ls


# -- one evaluation: residual spectrum and noise spectrum of a hypothesis -----------------------------------
class Evaluator:
    """Caches what does not change between evaluations (mean responses, parts of fixed effects),
    shared by the threads that fit one record's candidates (:class:`noiselab.memo.Memo`)."""

    def __init__(self, data: Data):
        self.data = data
        self._mean = Memo(17, flush=True)
        self._parts = W.parts_cache()
        self._pgram = Memo(9, flush=True)
        self._slope = Memo(17, flush=True)
        self._ramp = Memo(65, flush=True)
        self._level = Memo(65, flush=True)
        self._quant = Memo(9, flush=True)
        self._qmo = Memo(17, flush=True)
        self.evals = 0

    def quant_moments(self, model):
        """The quantizer's conditional moments over this record under ``model``
        (:meth:`Predictor.quantizer_moments`: they depend on its noise, not only on the mean
        effects) and a key for them; (None, None) when the error does not depend on the mean."""
        qid = of_kind(model.effects, "grid")
        if qid is None:
            return None, None
        # the sensor's white noise bounds the noise before the quantizer from below: above 0.84 step
        # no output's error depends on the mean (the common case, e.g. the seed's 10 steps)
        white = [np.asarray(s, float) ** 2 for s in (e.output_white_std() for e in model.effects.values())
                 if s is not None]
        if white and not _quant_mean_possible(_param(model, qid), sum(white[1:], white[0])):
            return None, None
        key = repr(model.to_dict())

        def compute():
            k0 = self.data.k0
            try:
                # over the analysed samples (its averages are the analysis'); g is 0 before them
                mo = model.predictor().quantizer_moments(self.mean(model)[0][k0:], k0)
            except (ValueError, np.linalg.LinAlgError):
                mo = None
            if mo is not None and k0:
                mo.g = np.concatenate([np.zeros((k0, mo.g.shape[1])), mo.g])
            return mo, None if mo is None else key
        return self._qmo.get_or_compute(key, compute)

    def residual_key(self, model, free_tone: bool) -> tuple:
        """:func:`_residual_key`, and the quantizer's moments when its mean depends on the noise."""
        return _residual_key(model, free_tone), self.quant_moments(model)[1]

    def mean(self, model):
        """E[y] and E[ydot]: cached without the sensor gain (a scale factor's trials share one
        response), the gain applied per model."""
        def compute():
            got = mean_response(model, self.data, gain=False)
            if self.data.free_start:
                # fitted to the record as it is (the sensor gain in it): the start state is fitted
                # per mean response, not per gain, and a gain's part of a decaying transient is small
                got = free_response_fit(model, self.data.y, *got, self.data.k0)
            return got
        y, yd = self._mean.get_or_compute(_mean_key(model, gain=False), compute)
        g = model.out_gain
        return (y, yd) if np.all(g == 1.0) else (y * g, yd * g)

    def parts(self, model, ydot_sq):
        """Per effect, the expected periodogram averaged over the frequency groups."""
        d = self.data
        return W.expected_parts(model, d.M, d.k0, d.at_rest, ydot_sq=ydot_sq, cache=self._parts, groups=d.groups,
                                cross=d.p > 1)

    def quant_part(self, model):
        """The quantizer's part of E I_f with its error correlated as the model predicts over this
        record (:mod:`noiselab.model.effects.sensor_quantization`: it depends on the other sources
        and on the record's mean response), or None where the plant has no stationary prediction.
        The mean response's factors are cached by the steps, the tones and the rms increments of
        the mean response (below)."""
        from ..model.effects.sensor_quantization import white_enough
        d = self.data
        pr = model.predictor()
        # white noises bound the variogram at lags >= 1 from below: often white already. Decided from
        # the parameters alone, before any steady state (a Lyapunov solution per call otherwise)
        qid = of_kind(model.effects, "grid")
        white = sum((np.broadcast_to(prm[0], (d.p,)) for eid, kind, *prm in pr._primitives()
                     if kind == "white" and eid != qid), np.zeros(d.p))
        step = _param(model, qid)
        mo = self.quant_moments(model)[0]
        if mo is None and white_enough(step, white):
            return None

        def variogram(K):
            gam = pr.variogram(K, quantization=False)
            return None if any(v is None for v in gam.values()) else gam

        K = int(min(d.M, QUANT_LAGS))
        gam = variogram(K)
        if gam is None or K < 2 or (mo is None and white_enough(step, np.min(pr.before_quantizer(gam)[1:], axis=0))):
            return None
        # the motion's factors cost transforms of the record's length: shared between mean responses
        # whose increments' rms agree to 3 significant digits at lags 1, 8, 64 and 512 (the searches
        # of a lag or a scale factor try many nearby ones; 1 - C_m changes with them at first order,
        # so the part is off by about 1 % at most)
        tone = _line(model)
        ym = self.mean(model)[0][d.k0:]
        inc = [np.sqrt(np.mean((ym[h:] - ym[:-h]) ** 2, axis=0)) for h in (1, 8, 64, 512) if h < ym.shape[0]]
        key = (tuple(float(f"{v:.3g}") for v in np.concatenate(inc)) if inc else (),
               repr(tone.param_dict()) if tone is not None else None,
               repr(step))
        motion, cache = self._quant.get_or_compute(key, lambda: (pr.motion(ym.shape[0], ym, d.k0), Memo(math.inf)))
        # one output: Stein's term in the part (negative where the quantizer holds the measurement;
        # Inner floors the total); several: carried by the noise parts instead (:func:`.hypotheses._stein`)
        multi = d.p > 1
        R = pr.quantization_acf(gam, motion, cache, mo, stein=not multi)
        if K < d.M and np.any(np.max(np.abs(R[3 * K // 4:]), axis=0) > QUANT_TAIL * np.max(np.abs(R), axis=0)):
            # still correlated at the last lags (a periodic command and a random part under a step:
            # the error holds the command's harmonics): every lag of the record, so that the
            # expected periodogram stays a spectrum (a cut one goes negative)
            R = pr.quantization_acf(variogram(d.M), motion, cache, mo, stein=not multi)
        return W.acf_part(R, d.M, d.groups, cross=multi, floor=multi or mo is None)

    def slope_power(self, model, ydot: np.ndarray) -> np.ndarray:
        """:func:`.whittle.slope_power` of the model's mean slope ``ydot``, cached by its mean response
        (it is an O(N) pass, and the evaluations of one diagnosis share few mean responses)."""
        return self._slope.get_or_compute(_mean_key(model), lambda: W.slope_power(ydot[self.data.k0:], self.data.p > 1))

    def grouped_periodogram(self, model, free_tone: bool):
        """:meth:`residual` and the group means of its periodogram, cached: only the mean effects
        and the tone change them, not the noise parameters most evaluations vary (except through a
        quantizer's conditional mean, :meth:`quant_moments`, when the noise is under a step)."""
        def compute():
            r, yd, fitted = self.residual(model, free_tone)
            # several outputs: the cross-periodogram matrices (the multivariate Whittle likelihood)
            I = W.periodogram(r, self.data.k0, cross=self.data.p > 1)
            return r, yd, fitted, self.data.group(I)
        r, yd, fitted, Ig = self._pgram.get_or_compute(self.residual_key(model, free_tone), compute)
        return r, yd, None if fitted is None else fitted.copy(), Ig

    def ramp_term(self, model, free_tone: bool) -> float:
        """l_ramp (:class:`.whittle.Ramps`) of the residual, cached like its periodogram."""
        ramps = self.data.ramps
        if not ramps:
            return 0.0
        return self._ramp.get_or_compute(
            self.residual_key(model, free_tone),
            lambda: ramps(np.diff(self.grouped_periodogram(model, free_tone)[0][self.data.k0:], axis=0)))

    def level_term(self, res_model, free_tone: bool, model) -> float:
        """l_level (:func:`.whittle.level_loglik`): the mean of ``res_model``'s residual against
        ``model``'s noise; 0 for a record not from rest or a sensor-only model (its absolute level
        is not predicted: :attr:`Model.predicts_level`) or a plant that is not stable (no stationary
        level: an integrator's walk), the same for every hypothesis of a record (they share the plant)."""
        d = self.data
        if not (d.at_rest and d.stable and model.predicts_level):
            return 0.0

        def compute():
            r, yd = self.grouped_periodogram(res_model, free_tone)[:2]
            return np.mean(r[d.k0:], axis=0), np.mean(yd[d.k0:] ** 2, axis=0)
        m, slope_sq = self._level.get_or_compute(("mean",) + self.residual_key(res_model, free_tone), compute)
        return W.level_loglik(m, *W.level_density(model, d.N - d.k0, slope_sq), d.N - d.k0)

    def residual(self, model, free_tone: bool):
        """r (N, p) with the tones removed, and the fitted line's amplitude (per output).
        A quantizer whose error depends on the mean (noise under about 0.84 step) adds its
        conditional mean E[Q(x)] - mu to the mean response (:meth:`quant_moments`)."""
        d = self.data
        ym, yd = self.mean(model)
        mo = self.quant_moments(model)[0]
        r = d.y - ym if mo is None else d.y - ym - mo.g
        tone = _line(model)
        fitted = None
        if tone is not None:
            # every line of the effect: the fitted one (its amplitude free with ``free_tone``), then
            # the others it holds (``repeatable``: found before it), each at its held amplitude
            lines = tone.all_lines() if type(tone).repeatable else \
                [(tone.params[type(tone).fit.scale], tone.params["frequency_hz"])]
            r = r.copy()
            for i, (amp_i, freq_i) in enumerate(lines):
                amp = np.broadcast_to(amp_i, (d.p,)).astype(float)
                freq = np.broadcast_to(freq_i, (d.p,)).astype(float)
                # a line before the sensor's own filter leaves it scaled by |H(f)|: the measurement's
                # amplitude is the model's times that (its parameter the one before the filter)
                gain = line_gain(model, tone.id, freq)
                free = free_tone and i == 0
                if i == 0:
                    fitted = amp.copy()
                for j in range(d.p):
                    a, b = tone_ls(r[:, j], freq[j], d.Ts, d.k0)
                    A = math.hypot(a, b)
                    if free:
                        fitted[j] = A / gain[j] if gain[j] > 0 else 0.0
                        scale = 1.0
                    else:
                        scale = amp[j] * gain[j] / A if A > 0 else 0.0
                    w = 2 * np.pi * freq[j] * d.Ts * np.arange(d.N)
                    r[:, j] -= scale * (a * np.sin(w) + b * np.cos(w))
        return r, yd, fitted


def _quant_mean_possible(step, white_var) -> bool:
    """Whether a white noise of variance ``white_var`` before a quantizer of ``step`` leaves its error's
    conditional mean on some output (:func:`.sensor_quantization.mean_matters`; other noise only lowers it)."""
    from ..model.effects.sensor_quantization import mean_matters
    return bool(np.any(mean_matters(step, white_var)))


def _param(model, eid: str):
    """Effect ``eid``'s scale parameter (``fit.scale``: a grid's step, a line's amplitude)."""
    eff = model.effects[eid]
    return eff.params[type(eff).fit.scale]


def _line(model):
    """The model's deterministic line (a ``line`` effect: a tone), or None."""
    eid = of_kind(model.effects, "line")
    return None if eid is None else model.effects[eid]


def _residual_key(model, free_tone: bool) -> tuple:
    """What the residual depends on: the mean response and the tone (fitted freely or held), and
    the sensor's own filter a tone passes (its amplitude in the measurement is |H(f)| times the
    model's)."""
    tone = _line(model)
    if tone is None:
        return _mean_key(model), None, free_tone
    flt = output_filter_of(model)
    return (_mean_key(model), repr(tone.param_dict()), free_tone,
            None if flt is None else repr(flt.param_dict()))
