"""Base class of the physical effects of DESIGN.md's catalogue.

Each effect is one module with one subclass of :class:`Effect` that knows its own physics:

* parsing and validating its TOML table (``__init__``),
* simulation, vectorized over a block of samples (``*_batch``) and one sample at a time
  (``*_step``), consuming ``n_normals`` standard normals per sample from the run's stream in the
  fixed ``draw_order`` of the catalogue (so the step and batch paths see the same draws),
* what it adds to the predictions, through one of the hooks below.

Signal chain at sample k (discrete time, sample period Ts):

    drive_k  = N(u_c,k + n_a,k)        actuator noises n_a (white, AR(1)) then static nonlinearities N
    x_{k+1}  = A_d x_k + B_d drive_k + process noise     (plant, with actuator lag states if any;
                                                           drive held over [k Ts, (k+1) Ts))
    y_k      = Q( (1 + s_f) (C x_k + D drive_k) + h * (b_k + beta_k + v_k + tone_k) + ydot_k dt_k )

h * (.) is the sensor's own digital filter (``sensor.filter``, identity when the model has none):
the transducer's noises, drifts and pick-up (the sources of chain orders 7-10) pass through it as
they pass through a MEMS IMU's DLPF / decimation filter between its ADC and its output register;
the quantizer Q acts on its output (the register word). The plant output and the jitter's term pass
unfiltered (exact for a static sensor; see :mod:`.sensor_filter`).

The AR(1) actuator noise is updated before it is used (seed section 10: u_act,k = u_k + n_{a,k+1})
and the bias walk is stepped after the measurement it enters, so y_k holds k bias increments.

Simulation hooks (the batch path and the step path call the same functions on blocks, so they
give identical floats): ``actuator_terms(e, state)`` / ``sensor_terms(e, state[, n])`` return what
a noise source adds for a block of its normals (trials, n, .); ``apply(u)`` is a static
nonlinearity (saturation, dead zone on the drive; quantization on y); the jitter gives
``time_errors(e)``. Sources do not depend on the plant state or the command, so the step path
computes them a buffer at a time.

Prediction hooks (implemented by the effects they concern; defaults contribute nothing):

* ``drive_linear()``: an actuator-noise source as a discrete linear system driven by its normals
  (states s, s_{k+1} = F s_k + G e_k, noise_k = C s_k + D e_k), per input channel.
* ``knots()``: a static actuator nonlinearity as a piecewise-linear map, for Gaussian expectations.
* ``augment()``: continuous states added to the plant (actuator lag).
* ``process_factor()``: the per-sample state-noise factor S (x_{k+1} += S e_k).
* ``sensor_linear()``: a sensor source with states (Gauss-Markov bias): (F, G, H), y += H s;
  ``initial_cov()``: the covariance of those states at k = 0 where the source starts stationary
  (a flicker bias), for the covariance recursion (without it they start at zero).
* ``output_filter()``: the sensor's own linear filter as (F_f, G_f, H_f, J_f) (s_f' = F_f s_f +
  G_f x, w = H_f s_f + J_f x), with ``gain(f)`` = |H| per output; the predictor cascades it with
  every sensor source of a lower ``chain_order`` (white primitives become sources of its states,
  tones are scaled by |H|); the simulation applies ``filter_terms(x, state)`` to those sources' sum.
* ``spectral()``: non-state contributions as primitives: ``("white", var)``, ``("walk", q, var0)``
  (increment variance q per sample, initial variance var0 = Var(b_0)), ``("tone", amplitude,
  frequency_hz)``, ``("jitter", s2)`` (white noise whose variance follows the signal's slope,
  s2 ydot_k^2: the comparison widens its estimators' spreads for that modulation).
* ``output_gain()``: a multiplicative modifier of the plant output (scale factor).
* ``time_errors(e)``: a sampling-time error dt_k per sample, entering y as ydot_k dt_k (jitter).

Prediction hooks that say how an effect takes part (class attributes and methods in the
"prediction hooks" section of :class:`Effect`, whose defaults contribute nothing):

* ``signal_dependent``: its prediction depends on the model's own mean response over the horizon
  (the jitter's slope, the quantizer's spread): the predictor computes that mean response only
  for a model with such an effect (or an actuator nonlinearity).
* ``acts_after_sum``: a static map of the measurement after every other term is summed
  (quantization, through ``apply(y)`` in the simulation). Its part of the second-order predictions
  is not independent of the others: :meth:`Effect.error_acf` forms it from the other effects'
  variogram and the deterministic motion, :meth:`Effect.error_moments` gives its conditional
  moments over a record's mean (its action on the mean), :meth:`Effect.moments_matter` whether a
  noise of a given variance leaves it any. At most one such effect is predicted (the last in the
  chain).
* ``without_plant``: why the effect cannot exist in a sensor-only model beyond its stage (process
  and actuator effects need a plant by their stage), or None.
* ``approximation_note(avg, others_var)``: one sentence on the approximation its prediction makes
  for this model (``avg``: the horizon averages of the mean response, ``others_var``: the variance
  the other effects add), or None.

Diagnosis hooks (how the effect is found and fitted from a residual, :mod:`noiselab.diagnose`).
The diagnosis never names an effect: it asks these, and each default contributes nothing.

* ``fit``: a :class:`FitSpec`: which parameter scales the noise variance, which are searched and
  over what range, which effect it can replace. Its ``kind`` also chooses the machinery the
  diagnosis applies to the effect:

  - ``noise``: a part of the expected periodogram linear in its variance (the inner fit);
  - ``mean``: the residual is recomputed per value of its searched parameters;
  - ``filter``: the sensor's own filter, a shape of the noises before it with no variance of its
    own: each of its ``fit_starts(Ts)`` (parameters, searched names) is a start (the kinds of
    filter, each moving average's taps), the best of them the candidate;
  - ``grid``: values on a grid of step ``fit.scale`` (quantization): the search starts at the
    record's own grid steps (:attr:`.data.Data.grid`), the likelihood adds l_grid, and the
    quantizer's conditional moments and correlated error (:class:`Predictor`'s quantizer terms)
    enter the residual and the parts, the noise parts carrying its Stein factors;
  - ``line``: a deterministic sinusoid of amplitude ``fit.scale`` and frequency ``frequency_hz``
    (a tone): removed from the residual by least squares, started at the periodogram's peaks
    (:func:`.tones.tone_peaks`), its frequency refined on the periodogram;
  - ``modulated``: a white noise whose variance follows the squared slope, scale ``fit.scale`` in s
    (jitter): its part from the mean slope, and the likelihood's modulation term
    (:class:`.modulation.Modulation`).

* ``channels``: how a fitted scale's variance splits over the channels: ``"output"`` (one per output:
  a sensor noise), ``"input"`` (one per input: an actuator noise), ``"noise_input"`` (one per
  process-noise input, a column of L), ``"one"`` (one factor; default).
* ``per_channel_mean``: a mean effect also offered with one searched value per channel (a limit per
  input, a scale factor per output).
* ``gain_start``: the searched parameter is a relative gain error e of the mean response
  (y = (1 + e) E[y]): its per-channel start is each output's least-squares e.
* ``drift``: the effect models a slow drift: ``"sensor"`` (a bias walk or Gauss-Markov bias, the
  usual model of one) or ``"actuator"`` (colored actuator noise, a drift through the plant's gain
  when slow); the search's drift rule (:meth:`.search.Search.drift_margin`) weighs one against the other.
* ``clips``: a static nonlinearity of the mean (saturation, dead zone): where the data cannot tell
  it from a linear effect, the linear one is reported.
* ``output_white_std()``: the std of a white noise the effect adds to each output before the
  quantizer (a lower bound of the noise there), or None.
* ``repeatable``: a ``line`` effect that holds several lines (a tone's harmonics, vibration
  lines), found one after another: ``all_lines()`` lists them as (amplitude, frequency_hz) per
  output, the fitted one (``fit.scale`` and ``frequency_hz``) first; ``push_line()`` gives the
  parameters with that one moved among the held lines (a new one is then set in its place),
  ``pop_line()`` undoes it.
* ``explain(params, Ts)``: one sentence of evidence in physical terms; ``equivalents(params, Ts)``:
  the same fit in the file's other spellings, e.g. ``rho`` for ``tau_s``, for users' scripts.

:func:`noiselab.model.effects.of_kind` finds the effect of a kind among a model's.

Spelling hooks: a parameter the file may give in another spelling (``sensor.white``'s ``density``
for its ``std``) is held in ``params`` under the catalogue's name, which the simulation, the
predictions and the diagnosis read; ``param_dict()`` writes it back as the file gave it, and
``respell(values)`` turns values set under the catalogue's names (a refit) into the file's
spelling, so a fitted model keeps the user's words.

IMU vocabulary: ``coefficients()`` gives the effect's IEEE Std 952 coefficients (N, K, B, ...) as
:class:`Coefficient` values per output (default: none); :mod:`noiselab.model.coefficients` collects
them for a model without naming any effect. A bias-instability effect (a flicker floor) would give
``B`` through the same hook.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ..schema import Table


@dataclass(frozen=True)
class FitSpec:
    """How the diagnosis fits an effect (see :mod:`noiselab.diagnose.search`).

    kind: ``noise`` (a source whose variance scales with ``scale``^2, fitted by the spectral
    likelihood), ``mean`` (changes the mean response to the command), ``grid`` (quantization: values
    on a grid of step ``scale``), ``line`` (a tone: a deterministic sinusoid in a record, amplitude
    ``scale``, frequency ``frequency_hz``), ``modulated`` (a noise source whose variance follows the
    signal's slope: jitter), ``filter`` (the sensor's own filter: a shape of the noises before
    it, started at each of the effect's ``fit_starts``); the kind chooses the diagnosis'
    machinery (module docstring).
    shape: searched parameters ``(name, lo, hi, unit, spacing)``: bounds in ``unit`` ("Ts": sample
    periods, "T": record lengths, "umax": the largest |command|, "fs": the sample rate, "1":
    absolute), ``spacing`` "log" or "lin".
    unit_scale: the reference value of ``scale`` ("Ts/10" for a value relative to Ts).
    replaces: effect ids this one may replace (white actuator noise that is really colored).
    needs_command: only identifiable when the record holds a varying command.
    """

    kind: str
    scale: str | None = None
    shape: tuple = ()
    unit_scale: float | str = 1.0
    replaces: tuple = ()
    needs_command: bool = False


@dataclass(frozen=True)
class Coefficient:
    """One IEEE Std 952 coefficient of an effect, one value per output.

    name: the IEEE 952 symbol (``N``, ``K``, ``B``) or, where IEEE 952 has none, the effect's own
    (``q``, ``sigma_GM``); unit: text in which ``{u}`` stands for the output's unit
    (``"{u}/sqrt(Hz)"`` -> ``rad/s/sqrt(Hz)``); param: the model-file parameter (catalogue
    spelling) it follows from, and ``of`` the map from that parameter's values to the
    coefficient's, increasing, so the parameter's interval maps end to end onto the
    coefficient's; white: True where it is (part of) the white-noise density seen by a user of N
    (Kalibr's noise density adds these in quadrature).
    """

    name: str
    value: np.ndarray
    unit: str
    param: str
    of: Callable[[np.ndarray], np.ndarray]
    white: bool = False


@dataclass(frozen=True)
class Dims:
    """Sizes and sampling the effects need: inputs m, outputs p, process-noise channels nw."""

    m: int
    p: int
    nw: int
    Ts: float
    discretization: str


class Effect:
    id: ClassVar[str] = ""
    stage: ClassVar[str] = ""          # "process" | "actuator" | "sensor"
    role: ClassVar[str] = "source"     # "source" adds noise; "modifier" changes how signals pass
    chain_order: ClassVar[int] = 0     # position in the signal chain (catalogue order)
    draw_order: ClassVar[int] = 99     # position in the per-sample block of normals
    summary: ClassVar[str] = ""
    linear: ClassVar[bool] = True      # False: predictions use an approximation (documented)
    fit: ClassVar[FitSpec] = FitSpec("none")

    def __init__(self, table: Table, dims: Dims):
        self.dims = dims
        self.params: dict[str, np.ndarray | float] = {}
        self.parse(table)
        table.done()

    def parse(self, table: Table) -> None:  # pragma: no cover - every effect overrides
        raise NotImplementedError

    # -- simulation -------------------------------------------------------------------------
    def n_normals(self) -> int:
        return 0

    def init_state(self, static_rng: np.random.Generator, trials: int) -> dict:
        """Per-run state (trials, ...). ``static_rng`` draws the run's static randoms."""
        return {}

    # -- prediction hooks (see the module docstring; the defaults contribute nothing) ------------
    signal_dependent: ClassVar[bool] = False
    acts_after_sum: ClassVar[bool] = False
    without_plant: ClassVar[str | None] = None

    def approximation_note(self, avg, others_var: np.ndarray) -> str | None:
        """A sentence on the approximation the prediction makes for this model; none by default."""

    def error_acf(self, gamma: np.ndarray, motion: np.ndarray | None, cache=None, moments=None,
                  cross: np.ndarray | None = None) -> np.ndarray:
        """R(d) (L, p) of an effect acting after the sum, from the variogram ``gamma`` (L, p) of the
        random part of the signal before it and the deterministic ``motion``; zero by default."""
        return np.zeros_like(np.asarray(gamma, float))

    def error_moments(self, mu: np.ndarray, sigma2: np.ndarray):
        """Conditional moments of an effect acting after the sum over a record whose mean before it
        is ``mu`` (n, p) and the random part's variance ``sigma2``; None by default."""

    def moments_matter(self, sigma2: np.ndarray) -> np.ndarray:
        """Per output, whether a noise of variance ``sigma2`` before this effect leaves it a
        conditional mean (:meth:`error_moments`); never by default."""
        return np.zeros(np.shape(sigma2), bool)

    # -- description ------------------------------------------------------------------------
    def param_dict(self) -> dict:
        """Parameters with the model file's names; scalars when every channel is equal."""
        return {k: _plain_value(v) for k, v in self.params.items()}

    def respell(self, values: dict) -> dict:
        """``values`` set under the catalogue's names (a diagnosis' refit), in the spelling this
        effect's file used (see the module docstring); by default the same."""
        return values

    # -- IEEE Std 952 coefficients ---------------------------------------------------------------
    def coefficients(self) -> list[Coefficient]:
        """The effect's IEEE Std 952 coefficients (:class:`Coefficient`); none by default."""
        return []

    # -- diagnosis hooks (module docstring) -------------------------------------------------------
    channels: ClassVar[str] = "one"          # "output" | "input" | "noise_input" | "one"
    per_channel_mean: ClassVar[bool] = False
    gain_start: ClassVar[bool] = False
    drift: ClassVar[str | None] = None       # "sensor" | "actuator" | None
    clips: ClassVar[bool] = False
    repeatable: ClassVar[bool] = False

    def output_white_std(self) -> np.ndarray | float | None:
        """The std of a white noise this effect adds to each output before the quantizer; None."""
        return None

    @classmethod
    def explain(cls, params: dict, Ts: float, ctx: dict | None = None) -> str:
        """One sentence of evidence for a fitted effect; ``ctx`` may hold ``band`` (f_lo, f_hi)
        where the data left the model."""
        return f"{cls.summary} ({', '.join(f'{k} = {_g(v)}' for k, v in params.items())})"

    @classmethod
    def equivalents(cls, params: dict, Ts: float) -> dict:
        """Other spellings of the same fitted values (added to the JSON report, not the file)."""
        return {}

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.param_dict()})"


def _plain_value(v):
    """A parameter vector as the file writes it: a float when every channel is equal, else a list."""
    a = np.atleast_1d(np.asarray(v, float))
    return float(a[0]) if np.all(a == a[0]) else [float(x) for x in a]


def _g(v) -> str:
    """A parameter for a sentence: 3 significant digits, lists element-wise, a choice (a filter's
    kind) as it is, a table (a tone's line) as its keys' values."""
    if isinstance(v, str):
        return v
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {_g(x)}" for k, x in v.items()) + "}"
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_g(x) for x in v) + "]"
    return f"{float(v):.3g}"


def band_phrase(ctx: dict | None) -> str:
    """"between f_lo and f_hi Hz, " where the effect holds most of the differenced residual's power
    (``ctx["band"]``, from the fit), or ""."""
    band = (ctx or {}).get("band")
    return f"between {_g(band[0])} and {_g(band[1])} Hz, " if band else ""


def tau_of(params: dict, Ts: float) -> np.ndarray:
    """A fitted AR(1) or Gauss-Markov correlation time (s), from ``tau_s`` or ``rho`` (per channel; NaN
    where rho is not in (0, 1))."""
    if "tau_s" in params:
        return np.atleast_1d(np.asarray(params["tau_s"], float))
    rho = np.atleast_1d(np.asarray(params["rho"], float))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where((rho > 0) & (rho < 1), -Ts / np.log(np.where(rho > 0, rho, 1.0)), np.nan)


def rho_tau_equivalents(params: dict, Ts: float) -> dict:
    """rho = exp(-Ts / tau_s) and back, for AR(1) and Gauss-Markov fits."""
    if "tau_s" in params and "rho" not in params:
        return {"rho": _map(lambda t: float(np.exp(-Ts / t)), params["tau_s"])}
    if "rho" in params and "tau_s" not in params:
        return {"tau_s": _map(lambda r: float(-Ts / np.log(r)) if 0 < r < 1 else float("nan"), params["rho"])}
    return {}


def _map(fn, v):
    return [fn(float(x)) for x in v] if isinstance(v, (list, tuple)) else fn(float(v))


TAU_MAX_TS = 1e15
"""The longest AR(1)/Gauss-Markov correlation time, in sample periods (see :func:`parse_rho_tau`)."""


def parse_rho_tau(table: Table, n: int, Ts: float) -> tuple[np.ndarray, np.ndarray]:
    """AR(1)/Gauss-Markov correlation: ``rho`` or ``tau_s`` (rho = exp(-Ts/tau_s)), exactly one."""
    if table.has("rho") == table.has("tau_s"):
        raise table.error("rho", "give exactly one of rho (per sample, |rho| < 1) or tau_s (s, > 0)")
    if table.has("rho"):
        rho = table.vector("rho", n, check=lambda v: bool(np.all(np.abs(v) < 1)), expect="|rho| < 1")
        with np.errstate(divide="ignore", over="ignore"):          # a huge Ts: tau = inf
            tau = np.where(rho > 0, -Ts / np.log(np.where(rho > 0, rho, 0.5)), np.nan)
        return rho, tau
    # rho = exp(-Ts / tau_s) must stay below 1 in float64 (Ts / tau_s above 2^-53): a longer
    # correlation time is a walk over any record, and rho = 1 makes the stationary covariance singular
    tau = table.vector("tau_s", n, check=lambda v: bool(np.all((v > 0) & (v <= TAU_MAX_TS * Ts))),
                       expect=f"time constants in s > 0 and at most {TAU_MAX_TS:g} Ts = {TAU_MAX_TS * Ts:g} s")
    return np.exp(-Ts / tau), tau
