"""The stochastic model: model files, plant, effect catalogue, discretization, simulation and
predictions. Pure math, no I/O beyond reading the model file."""

from .errors import ModelError
from .model import Model, dumps_toml, load_model, parse_model, scenario_names

__all__ = ["Model", "ModelError", "dumps_toml", "load_model", "parse_model", "scenario_names"]
