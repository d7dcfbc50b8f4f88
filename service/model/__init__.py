"""The stochastic model: model files, plant, effect catalogue, discretization, simulation and
predictions. Pure math, no I/O beyond reading the model file.

Names are resolved on first use (PEP 562), so importing :class:`ModelError` (every command's
error handling does) does not load scipy: nodes that never touch the model start fast.
"""

from .errors import ModelError

__all__ = ["Model", "ModelError", "dumps_toml", "load_model", "parse_model", "scenario_names"]


def __getattr__(name):
    if name in ("Model", "dumps_toml", "load_model", "parse_model", "scenario_names"):
        from . import model as _model
        return getattr(_model, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
