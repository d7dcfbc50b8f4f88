"""The effect catalogue (DESIGN.md): effect id -> class. A new effect is a new module listed here."""

from .actuator_ar1 import ActuatorAR1
from .actuator_deadzone import ActuatorDeadzone
from .actuator_lag import ActuatorLag
from .actuator_saturation import ActuatorSaturation
from .actuator_white import ActuatorWhite
from .base import Dims, Effect
from .process_white import ProcessWhite
from .sensor_bias_markov import SensorBiasMarkov
from .sensor_bias_walk import SensorBiasWalk
from .sensor_jitter import SensorJitter
from .sensor_quantization import SensorQuantization
from .sensor_scale_factor import SensorScaleFactor
from .sensor_tone import SensorTone
from .sensor_white import SensorWhite

CATALOGUE: dict[str, type[Effect]] = {
    cls.id: cls
    for cls in sorted(
        [ProcessWhite, ActuatorWhite, ActuatorAR1, ActuatorLag, ActuatorSaturation, ActuatorDeadzone,
         SensorScaleFactor, SensorBiasWalk, SensorBiasMarkov, SensorWhite, SensorTone, SensorJitter,
         SensorQuantization],
        key=lambda c: c.chain_order)
}

__all__ = ["CATALOGUE", "Dims", "Effect"]
