"""Model files: load, validate (in one place, via :mod:`.schema`), assemble, write back.

A model is a plant plus a set of effects (DESIGN.md); without [plant] a sensor-only model, whose
plant has no states and passes the reference through (:func:`.plant.no_plant`). :func:`load_model` accepts a path to a TOML
file or the name of a built-in scenario (``service/scenarios/<name>.toml``). Every problem is a
one-line :class:`ModelError`.

Assembled symbols -> attribute names (shapes; n_x = plant states + lag states):

=========  ===============  ==================================================================
symbol     attribute        meaning
=========  ===============  ==================================================================
A_c, B_c   ``Ac``, ``Bc``   continuous plant (+ lag) state and drive-input matrices
C, D       ``Cy``, ``Dy``   output matrix on the state and feedthrough of the drive (p, n_x)/(p, m)
L          ``L``            process-noise input (n_x, n_w)
A_d, B_d   ``Ad``, ``Bd``   discretized (zoh or euler) state and input matrices
G_d Q_w^½  ``S_proc``       per-sample process-noise factor: x_{k+1} += S_proc e_k, e_k ~ N(0, I)
1 + s_f    ``out_gain``     sensor gain (p,)
=========  ===============  ==================================================================
"""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from . import discretize
from .command import Command, parse_command, replay
from .controller import ControllerSpec, parse_controller
from .effects import CATALOGUE, Dims, Effect
from .errors import ModelError
from .outputs import Outputs, parse_outputs
from .plant import Plant, no_plant, parse_plant
from .schema import Table

NAME_RE = re.compile(r"^[A-Za-z0-9_-]+$")
GROUPS = ("process", "actuator", "sensor")

# The sample period's range (s). From 1 us (1 MHz): the wire's and MCAP's times are integer ns, and
# Ts rounds to the ns by at most 0.05 % there (at 1.5 ns by 33 %). Up to a day: MCAP's times are
# unsigned 64-bit ns (1.8e19 ns, 584 years), 2e5 samples at one a day; a slower sensor is no stream.
TS_MIN = 1e-6
TS_MAX = 86400.0


def scenario_names(group: str | None = None) -> list[str]:
    """Built-in scenarios: ``seed``, ``seed-nominal``, ... and, with ``group="hidden"``, the
    hidden-effect pairs of ``service/scenarios/hidden/`` (``hidden/<effect id>`` and
    ``hidden/<effect id>-nominal``, ``hidden/null-*``); ``group="hidden-closed"``: the same under
    feedback (a servo under its ``[controller]``, ``hidden-closed/<effect id>``, ...)."""
    pkg = resources.files("noiselab.scenarios")
    if group:
        pkg = pkg.joinpath(group)
        return sorted(f"{group}/{p.name[:-5]}" for p in pkg.iterdir() if p.name.endswith(".toml"))
    return sorted(p.name[:-5] for p in pkg.iterdir() if p.name.endswith(".toml"))


def _is_scenario(name: str) -> bool:
    group, _, rest = name.rpartition("/")
    if group not in ("", "hidden", "hidden-closed") or not rest:
        return False
    return name in scenario_names(group or None)


def scenario_text(name: str) -> str:
    return resources.files("noiselab.scenarios").joinpath(f"{name}.toml").read_text()


def load_model(spec: str | Path) -> "Model":
    """Load a model from a TOML path or a built-in scenario name (``seed``, ``seed-nominal``, ...)."""
    path = Path(spec)
    if path.suffix == ".toml" or path.exists():
        try:
            text = path.read_text()
        except FileNotFoundError:
            raise ModelError(f"{spec}: no such model file (built-in scenarios: {', '.join(scenario_names())})")
        except (OSError, UnicodeDecodeError) as exc:
            raise ModelError(f"{spec}: cannot read the model file ({type(exc).__name__}: {exc})")
        return parse_model(text, str(spec))
    if _is_scenario(str(spec)):
        return parse_model(scenario_text(str(spec)), f"scenario {spec}")
    raise ModelError(f"{spec}: no such model file or built-in scenario (built-in: {', '.join(scenario_names())}; "
                     "hidden-effect pairs: hidden/<effect id>, hidden/<effect id>-nominal, hidden/null-*)")


def parse_model(text: str, source: str = "<model>") -> "Model":
    try:
        data = tomllib.loads(text)
    except RecursionError:
        raise ModelError(f"{source}: invalid TOML: arrays or inline tables nested too deeply")
    except ValueError as exc:
        # TOMLDecodeError, or tomllib's bare ValueError for an integer literal of more than
        # sys.get_int_max_str_digits() digits
        raise ModelError(f"{source}: invalid TOML: {exc}")
    return _from_data(data, source, text)


def _plain(v):
    """TOML's own types for a value built in code (numpy scalars and arrays to floats and lists),
    so a model built from a dict validates exactly as one parsed from its text."""
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple, np.ndarray)):
        return [_plain(x) for x in v]
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return float(v)
    return v


def _from_data(data: dict, source: str, text: str) -> "Model":
    top = Table(data, "", source)
    name = top.string("name", pattern=lambda s: bool(NAME_RE.fullmatch(s)),
                      expect="a device name of letters, digits, '_' or '-'")
    description = top.string("description", "")
    top._absent("sampling", None)
    if "sampling" not in data:
        raise top.error("sampling", "missing required table [sampling] (with Ts)")
    samp = Table(data["sampling"], "sampling", source)
    Ts = samp.number("Ts", check=lambda v: TS_MIN <= v <= TS_MAX,
                     expect=f"a sample period in s > 0, between {TS_MIN:g} (1 MHz) and {TS_MAX:g} (a day)")
    disc = samp.string("discretization", "zoh", choices=("zoh", "euler"))
    samp.done()
    top._absent("plant", None)
    top._absent("outputs", None)
    out_table = Table(data["outputs"], "outputs", source) if "outputs" in data else None
    if "plant" in data:
        plant = parse_plant(Table(data["plant"], "plant", source))
        outputs = parse_outputs(out_table, plant.p, shorthand="A" not in data["plant"])
    elif out_table is None:
        raise top.error("plant", "missing required table [plant] (m, c, k or A, B, C), or [outputs] with "
                                 "names for a sensor-only model (y = reference + sensor effects)")
    else:
        outputs = parse_outputs(out_table, None, shorthand=False)
        plant = no_plant(len(outputs.names))
    top._absent("command", None)
    command = parse_command(Table(data["command"], "command", source) if "command" in data else None, plant.m, Ts)
    top._absent("controller", None)
    controller = parse_controller(Table(data["controller"], "controller", source) if "controller" in data else None,
                                  command.kind, plant.m, plant.p)
    dims = Dims(m=plant.m, p=plant.p, nw=plant.nw, Ts=Ts, discretization=disc)
    effects: dict[str, Effect] = {}
    for group in GROUPS:
        if top._absent(group, None):
            continue
        gt = data[group]
        if not isinstance(gt, dict):
            raise top.error(group, f"expected effect tables like [{group}.<effect>], got {gt!r:.40}")
        for sub, body in gt.items():
            eid = f"{group}.{sub}"
            if eid not in CATALOGUE:
                known = ", ".join(k for k in CATALOGUE if k.startswith(group + "."))
                raise ModelError(f"{source}: [{eid}]: unknown effect (known {group} effects: {known})")
            why = why_not_possible(eid, plant)
            if why:
                raise ModelError(f"{source}: [{eid}]: not possible in a model without [plant]: {why}")
            effects[eid] = CATALOGUE[eid](Table(body, eid, source), dims)
    top.done()
    ordered = {k: effects[k] for k in CATALOGUE if k in effects}
    return Model(name=name, description=description, Ts=Ts, discretization=disc, plant=plant,
                 command=command, effects=ordered, source=source, text=text, outputs=outputs,
                 controller=controller)


def why_not_possible(eid: str, plant: Plant) -> str | None:
    """Why effect ``eid`` cannot exist with ``plant`` (None: it can). Only a sensor-only model
    (:func:`.plant.no_plant`, y = reference + sensor effects) excludes effects: the ones that act
    on a plant's states or input, and the jitter, whose error dy/dt * dt needs a plant output's
    slope. The model file's parser refuses them and the diagnosis does not propose them."""
    if plant.has_states:
        return None
    group = eid.split(".", 1)[0]
    if group == "process":
        return "process noise drives the plant's states, and there are none"
    if group == "actuator":
        return "an actuator acts on the plant's input, and there is none (the command is the reference the sensor measures)"
    return CATALOGUE[eid].without_plant


@dataclass
class Model:
    """A validated, assembled model. Pure math: no I/O beyond what created it."""

    name: str
    Ts: float
    discretization: str
    plant: Plant
    command: Command
    effects: dict[str, Effect]
    source: str = "<model>"
    text: str = ""
    description: str = ""
    outputs: Outputs | None = None     # names and units of y (the [outputs] table or its defaults)
    controller: ControllerSpec | None = None   # the [controller] table: the default controller of `noiselab run`
    _asm: dict = field(default_factory=dict, repr=False)

    def __post_init__(self):
        if self.outputs is None:
            self.outputs = parse_outputs(None, self.plant.p, shorthand=self.plant.state_names == ("position", "velocity"))
        self._assemble()

    # -- assembly -----------------------------------------------------------------------------
    def _assemble(self) -> None:
        p = self.plant
        Ac, Bc, Cy, Dy, L = p.A, p.B, p.C, p.D, p.L
        for eff in self.effects.values():
            if hasattr(eff, "augment"):
                Ac, Bc, Cy, Dy, L = eff.augment(Ac, Bc, Cy, Dy, L)
        self.Ac, self.Bc, self.Cy, self.Dy, self.L = Ac, Bc, Cy, Dy, L
        # overflow in the matrix exponentials is not warned about but checked: a non-finite
        # result is a ModelError (here and in process.white), one line on the CLI
        with np.errstate(over="ignore", invalid="ignore"):
            if self.discretization == "euler":
                self.Ad, self.Bd = discretize.euler(Ac, Bc, self.Ts)
            else:
                self.Ad, self.Bd = discretize.zoh(Ac, Bc, self.Ts)
            if not (np.all(np.isfinite(self.Ad)) and np.all(np.isfinite(self.Bd))):
                raise ModelError(f"{self.source}: [plant] with [sampling] Ts = {self.Ts:g}: expected a plant whose "
                                 f"{self.discretization} discretization over Ts is finite, got an overflow "
                                 "(A Ts too large for float64)")
            # the per-sample state-noise sources (``process_factor``), their factors side by side
            self.proc_sources = [eff for eff in self.effects.values() if hasattr(eff, "process_factor")]
            factors = [eff.bind(Ac, L) for eff in self.proc_sources]
            self.S_proc = factors[0] if len(factors) == 1 else \
                np.hstack(factors) if factors else np.zeros((Ac.shape[0], 0))
            ends = np.cumsum([0] + [f.shape[1] for f in factors])
            self.proc_columns = {e.id: slice(int(a), int(b)) for e, a, b in zip(self.proc_sources, ends, ends[1:])}
        gain = np.ones(p.p)
        for eff in self.effects.values():
            if hasattr(eff, "output_gain"):
                gain = gain * eff.output_gain()
        self.out_gain = gain
        # the per-sample block of standard normals: effects in draw order
        layout, start = [], 0
        for eff in sorted(self.effects.values(), key=lambda e: e.draw_order):
            n = eff.n_normals()
            if n:
                layout.append((eff, slice(start, start + n)))
                start += n
        self.normal_layout = layout
        self.n_normals = start

    # -- sizes ----------------------------------------------------------------------------------
    @property
    def n_x(self) -> int:
        """Continuous-stage states (plant + actuator lag)."""
        return self.Ac.shape[0]

    @property
    def m(self) -> int:
        return self.plant.m

    @property
    def p(self) -> int:
        return self.plant.p

    @property
    def output_names(self) -> tuple[str, ...]:
        return self.outputs.names

    @property
    def output_units(self) -> tuple[str, ...]:
        return self.outputs.units

    @property
    def has_plant(self) -> bool:
        """False for a sensor-only model (no [plant]: y = reference + sensor effects)."""
        return self.plant.has_states

    @property
    def predicts_level(self) -> bool:
        """Whether the model predicts the absolute level of a record from rest (its mean response
        from a zero state), to which the analysis then holds the record's mean (the level view, the
        diagnosis' level term). With a plant it does. A sensor alone measures its reference plus a
        constant offset that no effect of the model holds (a gyro's turn-on bias, gravity on an
        accelerometer axis): its record's level is free and only what varies is compared."""
        return self.has_plant

    def can_have(self, eid: str) -> bool:
        """Whether effect ``eid`` may be in this model (:func:`why_not_possible`)."""
        return why_not_possible(eid, self.plant) is None

    def normal_layout_slot(self, eff: Effect) -> slice | None:
        """Columns of the per-sample normals block that belong to ``eff`` (None: it draws none)."""
        for e, sl in self.normal_layout:
            if e is eff:
                return sl
        return None

    def effects_in(self, stage: str) -> list[Effect]:
        return [e for e in self.effects.values() if e.stage == stage]

    # -- editing (diagnosis adds or changes effects) ------------------------------------------------
    def to_dict(self) -> dict:
        d: dict = {"name": self.name}
        if self.description:
            d["description"] = self.description
        d["sampling"] = {"Ts": self.Ts, "discretization": self.discretization}
        if self.has_plant:                               # a sensor-only model has no [plant]
            if "plant" not in self._asm:                 # the text is parsed once per model
                self._asm["plant"] = _plant_dict(self.plant, self.text, self.source)
            d["plant"] = dict(self._asm["plant"])
        if self.outputs.given or not self.has_plant:      # without a plant, [outputs] says what y is
            d["outputs"] = self.outputs.to_dict()
        d["command"] = _command_dict(self.command)
        if self.controller is not None:
            d["controller"] = self.controller.to_dict()
        for eid, eff in self.effects.items():
            g, s = eid.split(".")
            d.setdefault(g, {})[s] = eff.param_dict()
        return d

    def cache_key(self) -> str:
        """The model as a cache key (:class:`noiselab.memo.Memo`): its source and its content
        (:meth:`to_dict`, repr), formed once. Models of equal content predict alike, whatever text
        (comments, spelling) or object they came from; the source names them in error messages."""
        key = self._asm.get("key")
        if key is None:
            key = self._asm["key"] = repr((self.source, self.to_dict()))
        return key

    def to_toml(self) -> str:
        return dumps_toml(self.to_dict())

    def with_effect(self, eid: str, params: dict) -> "Model":
        _check_effect_id(eid)
        d = self.to_dict()
        g, s = eid.split(".")
        d.setdefault(g, {})[s] = params
        return parse_model(dumps_toml(d), f"{self.source} + [{eid}]")

    def with_params(self, eid: str, params: dict) -> "Model":
        """The model with effect ``eid``'s table replaced by ``params`` (added if absent): one
        parse, for the diagnosis' many trial models."""
        _check_effect_id(eid)
        d = self.to_dict()
        g, s = eid.split(".")
        d.setdefault(g, {})[s] = _plain(params)
        # validated from the dict itself (the same checks as its text; no TOML parse per trial)
        model = _from_data(d, self.source if "[" in self.source else f"{self.source} + fit", dumps_toml(d))
        if "plant" in d:
            model._asm["plant"] = d["plant"]
        return model

    def with_command(self, command: dict) -> "Model":
        """The model with its ``[command]`` table replaced by ``command`` (the diagnosis replays a
        record's command in it, :func:`.command.replay`, and gives the user's back)."""
        d = self.to_dict()
        d["command"] = dict(command)
        model = _from_data(d, self.source, dumps_toml(d))
        if "plant" in d:
            model._asm["plant"] = d["plant"]
        return model

    def replaying(self, u) -> "Model":
        """The model with its command replaying the recorded ``u`` (N, m) (:func:`.command.replay`)
        where the two differ, for the predictions of a record: an ``external`` command (a closed
        loop, a user's recording) is zero as the model computes it, and the nonlinearities' gains,
        the jitter's slope and the quantizer's spread are averages over the command (a dead zone's
        gain is P(|u + n| > w): about 0.05 at u = 0 for a noise n of std w / 2, about 0.8 over a
        servo's closed-loop record). The model itself where ``u`` is None or its own command."""
        if u is None:
            return self
        u = np.asarray(u, float).reshape(len(u), -1)
        own = self.command.values(0, len(u), self.Ts)
        if own.shape == u.shape and np.allclose(u, own, rtol=1e-6, atol=1e-9 * max(1.0, float(np.max(np.abs(u))))):
            return self
        return self.with_command({"kind": "external", "replay": replay(u)})

    def without_effect(self, eid: str) -> "Model":
        _check_effect_id(eid)
        d = self.to_dict()
        g, s = eid.split(".")
        d.get(g, {}).pop(s, None)
        if g in d and not d[g]:
            del d[g]
        return parse_model(dumps_toml(d), f"{self.source} - [{eid}]")

    # -- convenience front doors ----------------------------------------------------------------
    def simulate(self, n: int, *, seed=None, trials: int | None = None, command=None, normals=None,
                 block: int = 1 << 16):
        from .simulate import simulate
        return simulate(self, n, seed=seed, trials=trials, command=command, normals=normals, block=block)

    def simulate_blocks(self, n: int, *, seed=None, trials: int | None = None, command=None,
                        normals=None, block: int = 1 << 16):
        from .simulate import simulate_blocks
        return simulate_blocks(self, n, seed=seed, trials=trials, command=command, normals=normals, block=block)

    def stepper(self, seed=None, normals=None):
        from .simulate import Stepper
        return Stepper(self, seed=seed, normals=normals)

    def predictor(self):
        from .predict import Predictor
        return Predictor(self)


def _check_effect_id(eid: str) -> None:
    if eid not in CATALOGUE:
        raise ModelError(f"{eid!r}: unknown effect id (known: {', '.join(CATALOGUE)})")


def _plant_dict(plant: Plant, text: str, source: str) -> dict:
    try:
        raw = tomllib.loads(text).get("plant") if text else None
    except tomllib.TOMLDecodeError:
        raw = None
    if raw is not None:
        return raw
    return {"A": plant.A.tolist(), "B": plant.B.tolist(), "C": plant.C.tolist(), "D": plant.D.tolist(),
            "L": plant.L.tolist()}


def _command_dict(cmd: Command) -> dict:
    out: dict = {"kind": cmd.kind}
    for k, v in cmd.params.items():
        a = np.atleast_1d(np.asarray(v, float)) if not isinstance(v, (int, str)) else None
        if a is None:
            out[k] = v
        else:
            out[k] = float(a[0]) if np.all(a == a[0]) else [float(x) for x in a]
    return out


# -- a small TOML writer for the model schema (tables of scalars, strings and numeric arrays) ----
_ESCAPE = {"\\": "\\\\", '"': '\\"', "\n": "\\n", "\t": "\\t", "\r": "\\r"}


def _escape(ch: str) -> str:
    """One character of a TOML basic string: backslash, quote and the control characters TOML
    forbids there (U+0000..U+001F, U+007F) are escaped."""
    if ch in _ESCAPE:
        return _ESCAPE[ch]
    return f"\\u{ord(ch):04x}" if ord(ch) < 0x20 or ord(ch) == 0x7F else ch


def _fmt(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ModelError(f"cannot write a non-finite value {v!r} to a model file")
        return repr(v)
    if isinstance(v, str):
        return '"' + "".join(_escape(ch) for ch in v) + '"'
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_fmt(x.item() if isinstance(x, np.generic) else x) for x in v) + "]"
    if isinstance(v, np.generic):
        return _fmt(v.item())
    if isinstance(v, dict):            # an inline table (an element of a list of tables: a tone's lines)
        return "{" + ", ".join(f"{_key(k)} = {_fmt(x)}" for k, x in v.items()) + "}"
    raise ModelError(f"cannot write {type(v).__name__} to a model file")


def _key(k: str) -> str:
    """A TOML key: bare when it is one (letters, digits, _ and -), else quoted."""
    return k if k and all(ch.isalnum() or ch in "_-" for ch in k) and k.isascii() else _fmt(str(k))


def dumps_toml(d: dict) -> str:
    lines: list[str] = []

    def emit(prefix: str, table: dict) -> None:
        scalars = {k: v for k, v in table.items() if not isinstance(v, dict)}
        subs = {k: v for k, v in table.items() if isinstance(v, dict)}
        # an empty table is written too: a table's presence is meaningful (an effect is in the model)
        header = bool(prefix) and (bool(scalars) or not subs)
        if header:
            lines.append(f"[{prefix}]")
        for k, v in scalars.items():
            lines.append(f"{k} = {_fmt(v)}")
        if header or scalars:
            lines.append("")
        for k, v in subs.items():
            emit(f"{prefix}.{k}" if prefix else k, v)

    emit("", d)
    return "\n".join(lines).rstrip() + "\n"
