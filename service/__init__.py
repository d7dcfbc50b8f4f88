"""noiselab: a live emulator and model checker for noisy sensors and actuators on dynamic systems."""
