"""Model files shared by tests in several folders (the statistical tests, the live runs, the
analysis and the diagnosis)."""

from noiselab.model import parse_model

# Closed loop: the seed plant (m = 1.2 kg, c = 0.35 N s/m, k = 4 N/m), zoh, commands from Zenoh,
# modest noise: force noise of continuous two-sided intensity 1e-4 N^2/Hz, 2 mm white sensor
# noise, 1 mm quantization.
LOOP_TOML = """
name = "loop"
[sampling]
Ts = 0.01
discretization = "zoh"
[plant]
m = 1.2
c = 0.35
k = 4.0
[command]
kind = "external"
[process.white]
psd = 1e-4
[sensor.white]
std = 0.002
[sensor.quantization]
step = 0.001
"""


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


# An encoder-like sensor: a quantizer step of 0.5 over a sensor noise of 0.04 (0.08 step), a sine
# moving the mean across ~11 steps, so most of the quantizer's error is a function of the mean.
ENCODER_TOML = """name = "encoder"
[sampling]
Ts = 0.005
[plant]
m = 1.0
c = 2.0
k = 10.0
[command]
kind = "sine"
amplitude = 20.0
frequency_hz = 0.3
[process.white]
std = 0.05
[sensor.white]
std = 0.04
[sensor.quantization]
step = 0.5
"""
