"""Which physical effect is missing: fit every candidate of the catalogue, rank, add, repeat.

Hypotheses (:mod:`.hypotheses`) are compared by Delta BIC = 2 Delta l - k ln n (k free parameters
added, n the number of samples times outputs; Schwarz 1978), l the likelihood of
:mod:`.evaluator`. A candidate is added when its Delta BIC exceeds :data:`.thresholds.THRESHOLD`
(10: "very strong" evidence, Kass & Raftery 1995), then every parameter freed so far is refitted
jointly and the search repeats, so a second hidden effect is found with the first one's
parameters adjusted to it (an AR(1) that first took a bias walk's low-frequency power gives it
back). Candidates the data cannot tell apart are ranked by the rules beside :class:`Start`; the
revisit of a slow actuator drift as a sensor bias is :meth:`Search.drift_margin`. The intervals of
the final fit are :mod:`.intervals`'.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import numpy as np

from .. import parallel
from ..model import ModelError
from ..model.effects import CATALOGUE
from . import whittle as W
from .data import Data
from .edits import (
    COMMON,
    PER_CHANNEL,
    _scale_name,
    _set,
    _shape_value,
    _shape_values,
    _unit_scale,
    _vec,
    n_channels,
    per_input,
    shape_channels,
)
from .hypotheses import Fit, Hypotheses
from .modes import ADD, ADD_LINE, REFIT, Mode, replacing
from .sandwich import lr_spread
from .thresholds import (
    CHIBAR2_95,
    DISTINCT_Z,
    EXACT_TIE,
    HARMONICS,
    SLOW_DRIFT,
    THRESHOLD,
    TIE,
)
from .tones import tone_peaks

WORKERS = 2               # candidates fitted concurrently on long records (a forked process or threads)
PARALLEL_MIN = 50_000     # samples x outputs from which they are
SCREEN_N = 1 << 18        # records of at least 2 SCREEN_N samples are screened on their first SCREEN_N


# -- candidates ---------------------------------------------------------------------------------------------
@dataclass(eq=False)       # a candidate is itself (two lines of one effect share effect and mode)
class Candidate:
    effect: str
    mode: Mode                      # add | refit | replace:<effect id> (:mod:`.modes`)
    fit: Fit
    k: int                          # free parameters it adds
    score: float = float("nan")     # Delta BIC against the current hypothesis
    sel: float = float("nan")       # choice score among the significant (Search.choice)
    loglik: float = float("nan")
    alternatives: list = field(default_factory=list)   # other effects the data support as well
    full: bool = False              # fit is already the joint thorough refit (Search.refit_all)
    by_error: tuple | None = None   # added on the views' word: (model error before, after)



def drift(eid: str) -> str | None:
    """What slow drift effect ``eid`` models (``Effect.drift``): "sensor", "actuator" or None."""
    return CATALOGUE[eid].drift


def plant_time_constant(model) -> float:
    """The plant's slowest time constant, 1 / min(-Re lambda) over the eigenvalues of its
    continuous A, an actuator lag's state included (inf with an integrator or an unstable mode)."""
    A = np.asarray(model.Ac, float)
    if A.size == 0:
        return math.inf
    re = np.linalg.eigvals(A).real
    return math.inf if np.any(re >= 0) else float(1.0 / np.min(-re))


def exact_tie(c, lead, key) -> bool:
    """``c`` and ``lead`` are the same fit: scores within :data:`.thresholds.EXACT_TIE` with as many free
    parameters (identical spectra, e.g. process and actuator white noise through one input). Two
    candidates of different sizes within it are not a tie: their scores already weigh the extra
    parameter (a walk and a Gauss-Markov bias, whose choice score is the likelihood-ratio test of
    1/tau > 0, are as the test decides, not as the signal chain's order)."""
    # as a difference: scores of 1e16 (a model without sensor noise) have a spacing above 0.5
    return key(lead) - key(c) < EXACT_TIE and c.k == lead.k


# Near-ties (the data cannot tell the candidates apart, e.g. white actuator and process noise through
# the same input, or saturation, dead zone and scale factor under a two-level command) are ranked
# by: a replacement, then a changed value, then an addition (the fewest effects: a wrong value of
# an effect the user has explains the data with no new physics), then the signal chain's order;
# the others are reported as alternatives. An exact tie (identical spectra) between a new effect and
# a changed value goes to the new effect: nothing in the data contradicts the user's value.


@dataclass
class Start:
    """A candidate before fitting: its initial model and free parameters."""
    effect: str
    mode: Mode
    model: object
    free: dict
    k: int


class Search:
    """Greedy forward selection over the catalogue with joint refits (see the module docstring)."""

    def __init__(self, model, data: Data, log=None, n_full: int = 3):
        self.data = data
        self.H = Hypotheses(data, model)
        self.log = log or (lambda s: None)
        self.nominal = model
        self.n_full = n_full
        # threads pay off once an evaluation's arrays are large (their setup is ~1 ms)
        self.workers = min(WORKERS, os.cpu_count() or 1) if data.N * data.p >= PARALLEL_MIN else 1
        # a long record: candidates are screened on its first SCREEN_N samples (a valid likelihood of
        # that part), then scored on the whole record at the screened values; the leaders are fitted
        # on the whole record (see :meth:`candidates`)
        self.pool = parallel.Pool()           # the maps' workers and the calls beside them
        self.Hs = self.H
        if data.N >= 2 * SCREEN_N:
            part = Data(data.y[:SCREEN_N + 1], None if data.u is None else data.u[:SCREEN_N + 1], data.Ts,
                        data.at_rest, data.k0)
            self.Hs = Hypotheses(part, model)

    def start(self) -> Fit:
        return self.H.inner_fit(self.nominal, {})

    def score(self, fit: Fit, cur: Fit, k: int) -> float:
        """Delta BIC: whether the data support adding the candidate at all."""
        return 2 * (fit.loglik - cur.loglik) - k * math.log(self.data.n_bic)

    @staticmethod
    def choice(fit: Fit, cur: Fit, k: int) -> float:
        """Which of the significant candidates: 2 Delta l - k c, c = :data:`.thresholds.CHIBAR2_95`. Between
        nested alternatives (a walk and a Gauss-Markov bias, its long-tau limit 1/tau = 0; white and
        AR(1) actuator noise, its short-tau limit rho = 0) this is the likelihood-ratio test of the
        extra parameter at 5 %. That parameter's null value is on the boundary of its range (tau_s >
        0), so the statistic's null distribution is 1/2 chi2_0 + 1/2 chi2_1 (Self & Liang 1987), whose
        95 % point is 2.71, not chi2_1's 3.84. Delta BIC would ask ln n ~ 12 per parameter of it and
        keep the limit case, wrongly, for a correlation time that a record of 20 of them shows
        clearly."""
        return 2 * (fit.loglik - cur.loglik) - k * CHIBAR2_95

    def candidates(self, cur: Fit, bar: float = THRESHOLD) -> list[Candidate]:
        """Every candidate screened (its own parameters searched, the rest refitted only in their
        variances; on a long record on its first :data:`SCREEN_N` samples, then the variances
        refitted and the candidate scored on the whole record), then the ``n_full`` best fitted
        jointly with everything freed so far on the whole record (every searched parameter from a
        coarse grid). The significant ones (Delta BIC > :data:`.thresholds.THRESHOLD`) come
        first, ranked by :meth:`choice`, the others by Delta BIC; near-ties (within :data:`.thresholds.TIE`)
        resolved towards fewer effects: a replacement first, then a changed value, then an
        addition; within a mode the best score, and the signal chain's order on an exact tie
        (:data:`.thresholds.EXACT_TIE`). ``bar``: the Delta BIC that counts as significant (the model-error rule
        of :func:`.diagnose._by_error` ranks every candidate by the choice score: ``-inf``)."""
        out = self._screened(cur, bar)
        out.sort(key=lambda c: -c.score)
        # the two forms of a noise of several inputs (per input or one factor) and of a mean effect
        # of several channels (one value per channel or one for all): the better by Delta BIC
        best: dict = {}
        for c in out:
            best.setdefault((c.effect, c.mode), c)
        two = {(c.effect, c.mode) for c in out if per_input(c.effect) or PER_CHANNEL in c.start.free.get(c.effect, ())
               or CATALOGUE[c.effect].fit.kind == "filter"}       # a filter's kinds and taps: its best start
        out = [c for c in out if (c.effect, c.mode) not in two or best[(c.effect, c.mode)] is c]
        leaders = [c for c in out[:self.n_full] if c.score >= bar - 30]

        def full_fit(c):
            try:
                return self.refit_all(c.fit, thorough=True)
            except (ModelError, ValueError, np.linalg.LinAlgError):
                return None

        for c, full in zip(leaders, self._map(full_fit, leaders)):
            if full is not None and full.loglik > c.fit.loglik:
                c.fit = full
                c.score = self.score(full, cur, c.k)
                c.full = True
        for c in out:
            c.loglik = c.fit.loglik
            c.sel = self.choice(c.fit, cur, c.k)
        return self._ranked(out, bar)

    def _screened(self, cur: Fit, bar: float) -> list[Candidate]:
        """Every start of :meth:`starts` screened (:meth:`candidates`) and scored, unsorted."""
        out: list[Candidate] = []
        starts = self.starts(cur)

        def screen(st):
            try:
                # a mean effect beside mean effects already fitted: searched jointly with them (a lag
                # fitted alone takes the amplitude loss a saturation causes; adding the saturation to
                # that lag only makes it worse until the lag gives it back)
                others = tuple(e for e in cur.free if e != st.effect and CATALOGUE[e].fit.kind == "mean"
                               and CATALOGUE[e].fit.shape)
                Hs = self.Hs
                if CATALOGUE[st.effect].fit.kind == "mean" and others:
                    fit = Hs.fit(st.model, st.free, new=(st.effect,) + others, only=(st.effect,) + others)
                else:
                    fit = Hs.fit(st.model, st.free, new=(st.effect,), screen=True)
                return fit if Hs is self.H else self.H.inner_fit(fit.model, fit.free)
            except (ModelError, ValueError, np.linalg.LinAlgError) as exc:
                return exc

        def screen_cost(st):
            spec = CATALOGUE[st.effect].fit
            return (3 if spec.kind == "mean" else 1) * (1 + len(spec.shape)) + (2 if spec.kind == "line" else 0)

        def per_input_form(st):
            return PER_CHANNEL in st.free.get(st.effect, ()) and CATALOGUE[st.effect].stage == "actuator"

        # an actuator mean effect's per-input form (a grid per input: the dearest screen) only where
        # its one-value form comes near significance (two limits clip alike: one value finds both)
        first = [st for st in starts if not per_input_form(st)]
        todo = [(first, self._map(screen, first, cost=screen_cost))]
        near = set()
        for st, fit in zip(*todo[0]):
            if not isinstance(fit, Exception) and self.score(fit, cur, st.k) >= bar - 30:
                near.add((st.effect, st.mode))
        later = [st for st in starts if per_input_form(st) and (st.effect, st.mode) in near]
        if later:
            todo.append((later, self._map(screen, later, cost=screen_cost)))
        for st, fit in ((st, fit) for sts, fits in todo for st, fit in zip(sts, fits)):
            if isinstance(fit, Exception):
                self.log(f"candidate {st.mode} {st.effect}: skipped ({fit})")
                continue
            c = Candidate(st.effect, st.mode, fit, st.k)
            c.score = self.score(fit, cur, st.k)
            c.start = st
            out.append(c)
        return out

    def _ranked(self, out: list[Candidate], bar: float) -> list[Candidate]:
        """The candidates in :meth:`candidates`' order, each near-tie's alternatives set."""
        # significant candidates first, ranked by the choice score; the rest by Delta BIC
        out.sort(key=lambda c: (c.score < bar, -(c.sel if c.score >= bar else c.score)))
        if out:
            key = (lambda c: c.sel) if out[0].score >= bar else (lambda c: c.score)
            top = key(out[0])
            near = [c for c in out if top - key(c) < TIE and (c.score >= bar) == (out[0].score >= bar)]
            # the preferred mode first; within it the best score, and on an exact tie (identical
            # spectra, e.g. process and actuator white noise through the same input) chain order
            rank = min(c.mode.rank for c in near)
            same = [c for c in near if c.mode.rank == rank]
            lead = max(same, key=key)
            first = min((c for c in same if exact_tie(c, lead, key)), key=lambda c: CATALOGUE[c.effect].chain_order)
            sig = out[0].score >= bar
            first = self._drift_as_bias(first, [c for c in out if (c.score >= bar) == sig
                                                and c.mode.rank == rank], key)
            # an exact tie between a new effect and a changed value (identical spectra): the data do
            # not contradict the user's value, so it is kept and the effect is added. The leader's tie
            # first, then the chosen candidate's: a third candidate leading (an AR(1) 0.8 ahead in the
            # choice score, its extra parameter near the test's level) used to hide the latter, and
            # a refit of process noise was taken over the added actuator noise it is identical with
            for anchor in (max(near, key=key), first):
                exact = [c for c in near if exact_tie(c, anchor, key) and exact_tie(anchor, c, key)]
                if {"add", "refit"} <= {c.mode.kind for c in exact}:
                    first = min(exact, key=lambda c: (c.mode.exact_rank, CATALOGUE[c.effect].chain_order))
                    break
            near = [first] + [c for c in near if c is not first]
            first.alternatives = [c for c in near[1:] if c.effect != first.effect]
            out.remove(first)
            out.insert(0, first)
        return out

    def drift_margin(self, ar1: Fit, bias: Fit) -> float | None:
        """Colored actuator noise whose correlation time exceeds :data:`.thresholds.SLOW_DRIFT` times the
        plant's slowest time constant reaches the output through the plant's low-frequency gain
        alone: a drift the data can hardly tell from a sensor bias drift (a Gauss-Markov bias, or
        the walk, its long-tau limit), the usual model of such a drift. The margin (in the units of
        :meth:`choice`) by which the AR(1) fit ``ar1`` must beat the bias fit ``bias`` to be
        reported instead: :data:`.thresholds.TIE`, or :data:`.thresholds.DISTINCT_Z` standard deviations of the likelihood
        ratio between the two (:func:`.sandwich.lr_spread`) when larger (on the generated Gauss-Markov cases
        the AR(1)'s lead reached 2.2 with a spread of 2.1). None when the AR(1) is not that slow."""
        eid = next(e for e in ar1.model.effects if drift(e) == "actuator")
        tau = _shape_value(ar1.model.effects[eid], "tau_s", self.data.Ts)
        if tau is None or not tau > SLOW_DRIFT * plant_time_constant(self.nominal):
            return None
        return max(TIE, DISTINCT_Z * (lr_spread(ar1, bias) or 0.0))

    def _drift_as_bias(self, first: Candidate, pool: list, key) -> Candidate:
        """A slow actuator AR(1) on top gives way to the better supported of the sensor bias
        candidates it does not beat by :meth:`drift_margin`. ``pool``: the candidates of the
        first's mode and significance."""
        if drift(first.effect) != "actuator":
            return first
        bias = []
        for c in pool:
            if drift(c.effect) == "sensor":
                margin = self.drift_margin(first.fit, c.fit)
                if margin is not None and key(first) - key(c) < margin:
                    bias.append(c)
        return max(bias, key=key) if bias else first

    def beside(self, fn):
        """fn() beside the search's maps (:meth:`noiselab.parallel.Pool.beside`): one more item of
        the next map that forks, a thread where it cannot, or now with one worker."""
        return self.pool.beside(fn, workers=self.workers)

    def _map(self, fn, items: list, cost=None) -> list:
        """fn over items, two at a time on long records (:meth:`noiselab.parallel.Pool.map`: in this
        process and a forked copy of it where that is safe, the fits being mostly Python, which
        threads cannot run at once; else in :data:`WORKERS` threads); results in order. ``cost``:
        an item's expected cost, the costliest started first (no worker idles at the end while the
        other runs a long fit)."""
        order = sorted(range(len(items)), key=lambda i: -cost(items[i])) if cost else None
        return self.pool.map(fn, items, workers=self.workers, order=order, portable=_portable, carry=self._carry())

    def _carry(self):
        """(mark, take, give) of :meth:`.parallel.Pool.map`: the parts a forked child computed
        (:meth:`.evaluator.Evaluator.parts`' cache, of the whole record and of the screened prefix) come back
        to this process, so that the next map's fits find them. The joint refits of a step's
        leaders share every correlation time of their coarse grids, and later steps' refits the
        same again: without this, each forked refit recomputes what an earlier one already had."""
        caches = [ev._parts for ev in {id(h.ev): h.ev for h in (self.H, self.Hs)}.values()]

        def mark():
            return [set(c.keys()) for c in caches]

        def take(marks):
            return [{k: v for k, v in c.items() if k not in m} for c, m in zip(caches, marks)]

        def give(brought):
            for c, new in zip(caches, brought):
                c.update(new)
        return mark, take, give

    def starts(self, cur: Fit) -> list[Start]:
        d = self.data
        out: list[Start] = []
        model = cur.model
        for eid, cls in CATALOGUE.items():
            spec = cls.fit
            if spec.kind == "line" and cls.repeatable and eid in model.effects:
                # one more line beside those the model holds (found before, or the user's)
                try:
                    out += self._tones(cur, eid, ADD_LINE)
                except (ModelError, ValueError, np.linalg.LinAlgError) as exc:
                    self.log(f"candidate {eid} (another line): skipped ({exc})")
            if spec.kind == "none" or eid in cur.free:
                continue
            if not model.can_have(eid):         # e.g. an actuator in a sensor-only model: none is there
                continue
            if spec.needs_command and not d.has_command:
                continue
            mode = REFIT if eid in model.effects else ADD
            try:
                if spec.kind in ("noise", "modulated", "mean"):
                    out += self._noise_or_mean(cur, eid, mode)
                    for rep in spec.replaces:
                        if mode == ADD and rep in model.effects and rep not in cur.free:
                            out += self._noise_or_mean(cur, eid, replacing(rep))
                elif spec.kind == "grid":
                    out += self._grid(cur, eid, mode)
                elif spec.kind == "line":
                    out += self._tones(cur, eid, mode)
                elif spec.kind == "filter" and mode == ADD:
                    out += self._filters(cur, eid)
            except (ModelError, ValueError, np.linalg.LinAlgError) as exc:
                self.log(f"candidate {eid}: skipped ({exc})")
        return out

    def _noise_or_mean(self, cur: Fit, eid: str, mode: Mode) -> list[Start]:
        d = self.data
        spec = CATALOGUE[eid].fit
        model = cur.model
        if mode.replaces is not None:
            model = model.without_effect(mode.replaces)
        names = []
        init: dict = {}
        if spec.kind in ("noise", "modulated"):
            if mode == REFIT:
                sname, _ = _scale_name(model.effects[eid])
            else:
                sname = spec.scale
                init[sname] = _unit_scale(spec, d.Ts) * (1e-3 if spec.kind == "noise" else 1e-1)
            names.append(sname)
        for sh in spec.shape:
            lo, hi, spacing = self.H._bounds(sh)
            if hi <= lo:
                return []
            names.append(sh[0])
            cur_v = None
            if mode == REFIT:
                cur_v = _shape_value(model.effects[eid], sh[0], d.Ts)
            init[sh[0]] = cur_v if cur_v is not None else \
                (math.sqrt(lo * hi) if spacing == "log" else 0.5 * (lo + hi))
        m = _set(model, eid, init) if init else model
        free = dict(cur.free)
        free[eid] = names
        nc = n_channels(model, eid) if spec.kind == "noise" else 1
        out = [Start(eid, mode, m, free, len(names) + nc - 1)]
        ns = shape_channels(model, eid) if CATALOGUE[eid].per_channel_mean else 1
        if ns > 1:
            # a mean effect of several inputs or outputs: also one value per channel (a saturation
            # limit per input, a scale factor per output; the file's values for a refit), each a
            # parameter for Delta BIC; :meth:`candidates` keeps the better supported of the two
            mc = m
            if mode == REFIT:
                for sh in spec.shape:
                    v = _shape_values(model.effects[eid], sh[0], d.Ts)
                    if v is not None and v.size == ns:
                        mc = _set(mc, eid, {sh[0]: _vec(v)})
            elif CATALOGUE[eid].gain_start:
                # linear in the residual: each output's least-squares factor on the mean response
                # (a grid cannot start near it when the response is far above the noise)
                mc = _set(mc, eid, {spec.shape[0][0]: _vec(self._scale_ls(model, spec.shape[0]))})
            out.append(Start(eid, mode, mc, dict(free, **{eid: names + [PER_CHANNEL]}), len(names) * ns))
        if nc > 1 and per_input(eid):
            # a noise of several inputs: also one factor over them (the file's proportions, equal for
            # a new effect); :meth:`candidates` keeps the better supported of the two. Where inputs
            # reach the outputs alike their variances are not told apart, and a per-input fit put
            # all of an equal noise on one of them
            out.append(Start(eid, mode, m, dict(free, **{eid: names + [COMMON]}), len(names)))
        return out

    def _scale_ls(self, model, shape) -> np.ndarray:
        """Per output, the least-squares scale-factor error e of y - E[y] = e E[y] (both centered,
        from sample k0), within the search's range of the searched parameter ``shape``."""
        d = self.data
        ym, _ = self.H.ev.mean(model)
        a = ym[d.k0:] - ym[d.k0:].mean(axis=0)
        r = d.y[d.k0:] - ym[d.k0:]
        r = r - r.mean(axis=0)
        den = np.sum(a * a, axis=0)
        e = np.where(den > 0, np.sum(r * a, axis=0) / np.where(den > 0, den, 1.0), 0.0)
        lo, hi, _ = self.H._bounds(shape)
        return np.clip(e, lo, hi)

    def _grid(self, cur: Fit, eid: str, mode: Mode) -> list[Start]:
        """A ``grid`` effect (quantization): started at the record's own grid steps (:attr:`.data.Data.grid`)."""
        d = self.data
        steps = d.grid
        if any(s is None for s in steps):
            return []
        sname = CATALOGUE[eid].fit.scale
        q = cur.model.effects.get(eid)
        if q is not None and np.allclose(np.broadcast_to(q.params[sname], (d.p,)), steps, rtol=1e-6):
            return []
        m = _set(cur.model, eid, {sname: _vec(steps)})
        free = dict(cur.free)
        free[eid] = []
        return [Start(eid, mode, m, free, d.p)]

    def _tones(self, cur: Fit, eid: str, mode: Mode) -> list[Start]:
        """A ``line`` effect (a tone): started at each peak of the residual's periodogram that no
        noise explains (:func:`.tones.tone_peaks`). ``ADD_LINE``: a line more of an effect of
        several (``repeatable``) that the model has, the residual being that of every line it holds,
        their frequencies left out of the peaks as the command's are; the lines it holds are kept
        at their values (``push_line``) and the new one is fitted."""
        d = self.data
        aname = CATALOGUE[eid].fit.scale
        free = dict(cur.free)
        free[eid] = [aname, "frequency_hz"]
        if mode == REFIT:
            return [Start(eid, mode, cur.model, free, 2 * d.p)]
        held, held_half = np.zeros(0), np.zeros(0)
        if mode.line:
            held, held_half = self._held_zones(cur.model, eid)
        r, _, _ = self.H.ev.residual(cur.model, False)
        I = W.periodogram(r, d.k0)
        E = sum(W.expected_parts(cur.model, d.M, d.k0, d.at_rest, cache=self.H.ev._parts,
                                 ydot_sq=W.slope_power(self.H.ev.mean(cur.model)[1][d.k0:], False)).values())
        out = []
        # a line at a frequency (or harmonic) of the command's own lines is the mean response's error
        # (a lag, a gain, a saturation's odd harmonics), not an interference tone
        lines = d.reference_lines()
        order = np.arange(1, HARMONICS + 1)
        harm = np.outer(lines, order).ravel()
        # zone: the main lobe of an off-bin line (+-2.5 bins) and the line's frequency known to half a
        # bin, times the harmonic's order
        half = np.broadcast_to(2.5 + 0.5 * order, (lines.size, order.size)).ravel()
        keep = harm < 0.5 / d.Ts
        harm, half = harm[keep], half[keep]
        if harm.size and not mode.line:
            self.log(f"tone candidates: none at the command's lines and their harmonics "
                     f"({', '.join(f'{x:.4g}' for x in harm[:4])}{', ...' if harm.size > 4 else ''} Hz)")
        # a line the model holds: its main lobe, the frequency's uncertainty and its wander over the
        # record (:meth:`_held_zones`); what is left there is that line's, not another's
        harm, half = np.concatenate([harm, held]), np.concatenate([half, held_half])
        for j, f in tone_peaks(I, E, d.M, d.Ts, exclude=(harm, half)):
            amp = np.zeros(d.p)
            amp[j] = 1.0
            new = {aname: _vec(amp), "frequency_hz": _vec(np.full(d.p, f))}
            if mode.line:
                m = cur.model.with_params(eid, dict(cur.model.effects[eid].push_line(), **new))
            else:
                m = _set(cur.model, eid, new)
            out.append(Start(eid, mode, m, free, 3))
        return out

    def _filters(self, cur: Fit, eid: str) -> list[Start]:
        """A ``filter`` effect (the sensor's own): a start per kind it offers (``fit_starts``), the
        noises before it refitted in their variances; one parameter each (a cutoff, or the taps
        chosen among the starts)."""
        out = []
        for params, names in CATALOGUE[eid].fit_starts(self.data.Ts):
            free = dict(cur.free)
            free[eid] = list(names)
            out.append(Start(eid, ADD, cur.model.with_effect(eid, params), free, 1))
        return out

    def _held_zones(self, model, eid: str) -> tuple[np.ndarray, np.ndarray]:
        """(frequencies Hz, half-widths in bins) of the lines effect ``eid`` holds, per output: each
        line's main lobe and frequency uncertainty (+-3 bins, as a command line's) plus its wander,
        twice the difference of its frequency fitted on the record's halves
        (:func:`.intervals.line_halves`: a drift's halves sit at a quarter and three quarters of
        its span). A line that wanders leaves power beside its fitted frequency; taken for
        another line, it split one wandering line into two steady ones."""
        from .intervals import line_halves
        d = self.data
        eff = model.effects[eid]
        freqs, halves = [], []
        for k, (_, f) in enumerate(eff.all_lines()):
            f = np.broadcast_to(f, (d.p,))
            h = line_halves(self.H, model, eid, k)
            for j in range(d.p):
                wander = 0.0 if h[j] is None else 2.0 * abs(h[j][0][0] - h[j][1][0]) * d.M * d.Ts
                freqs.append(float(f[j]))
                halves.append(3.0 + wander)
        return np.array(freqs), np.array(halves)

    def refit_all(self, cur: Fit, thorough: bool = False) -> Fit:
        """Refit every free parameter jointly. Searched parameters move locally from their current
        values; ``thorough``: each first gets a coarse grid over its whole range (after an effect is
        added or removed, where an earlier effect may have taken its power with a very different
        shape, e.g. an AR(1) that stretched its correlation time to stand in for a missing walk)."""
        new = tuple(e for e in cur.free if CATALOGUE[e].fit.shape) if thorough else ()
        return self.H.fit(cur.model, cur.free, rounds=2, new=new)


# -- a forked second process for the candidate maps ---------------------------------------------------
def _portable(x):
    """A map's result made ready to cross to the parent: a :class:`.hypotheses.Fit`'s level computed (its
    closure over this process' caches does not travel), recursively in lists, tuples and dicts."""
    if isinstance(x, Fit):
        _ = x.level
        x.level_fn = None
        return x
    if isinstance(x, (list, tuple)):
        return type(x)(_portable(v) for v in x)
    if isinstance(x, dict):
        return {k: _portable(v) for k, v in x.items()}
    return x
