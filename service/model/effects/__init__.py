"""The effect catalogue (DESIGN.md): effect id -> class. A new effect is a new module listed here."""

from .actuator_ar1 import ActuatorAR1
from .actuator_deadzone import ActuatorDeadzone
from .actuator_lag import ActuatorLag
from .actuator_saturation import ActuatorSaturation
from .actuator_white import ActuatorWhite
from .base import Dims, Effect
from .process_white import ProcessWhite
from .sensor_bias_instability import SensorBiasInstability
from .sensor_bias_markov import SensorBiasMarkov
from .sensor_bias_walk import SensorBiasWalk
from .sensor_filter import SensorFilter
from .sensor_integral_white import SensorIntegralWhite
from .sensor_jitter import SensorJitter
from .sensor_quantization import SensorQuantization
from .sensor_scale_factor import SensorScaleFactor
from .sensor_tone import SensorTone
from .sensor_white import SensorWhite

CATALOGUE: dict[str, type[Effect]] = {
    cls.id: cls
    for cls in sorted(
        [ProcessWhite, ActuatorWhite, ActuatorAR1, ActuatorLag, ActuatorSaturation, ActuatorDeadzone,
         SensorScaleFactor, SensorBiasWalk, SensorBiasMarkov, SensorBiasInstability, SensorWhite,
         SensorIntegralWhite, SensorTone,
         SensorFilter, SensorJitter, SensorQuantization],
        key=lambda c: c.chain_order)
}



def of_kind(ids, kind: str) -> str | None:
    """The id of the effect among ``ids`` (effect ids, or a dict keyed by them: a model's effects, a
    fit's free parameters) whose :class:`~.base.FitSpec` kind is ``kind``, the first of
    ``ids``; None when there is none. How the diagnosis finds the effect a kind's machinery
    applies to (:mod:`.base`, diagnosis hooks) without naming it."""
    for eid in ids:
        cls = CATALOGUE.get(eid)
        if cls is not None and cls.fit.kind == kind:
            return eid
    return None


__all__ = ["CATALOGUE", "Dims", "Effect", "of_kind"]
