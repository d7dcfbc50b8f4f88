"""Model files shared by the statistical tests."""

from service.model import parse_model

# A general two-output plant in zoh mode with every linear effect, plus tone and jitter.
ALL_LINEAR = """
name = "all"
[sampling]
Ts = 0.005
[plant]
A = [[0.0, 1.0], [-6.0, -0.9]]
B = [[0.0], [1.5]]
C = [[1.0, 0.0], [0.0, 0.3]]
[command]
kind = "sine"
amplitude = 0.5
frequency_hz = 0.9
[process.white]
psd = 0.02
[actuator.white]
std = 0.05
[actuator.ar1]
std = 0.1
tau_s = 0.2
[actuator.lag]
tau_s = 0.05
[sensor.scale_factor]
error = [0.03, -0.02]
[sensor.bias_walk]
std = [0.001, 0.002]
initial_std = 0.001
[sensor.bias_markov]
std = [0.004, 0.002]
tau_s = 1.5
[sensor.white]
std = [0.003, 0.004]
[sensor.tone]
amplitude = [0.002, 0.003]
frequency_hz = [7.0, 13.0]
[sensor.jitter]
std_s = 0.0004
"""

EVERYTHING = ALL_LINEAR.replace('name = "all"', 'name = "everything"') + """
[actuator.saturation]
limit = 0.9
[actuator.deadzone]
width = 0.02
[sensor.quantization]
step = 0.0005
"""


def load(text, name="test"):
    return parse_model(text, name)
