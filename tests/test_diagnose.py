"""Diagnosis (issue 5): the lesson case, a right model, the quantization grid."""

import numpy as np
import pytest

from service.model import load_model
from service.diagnose.diagnose import diagnose
from service.diagnose.search import quantization_grid


@pytest.fixture(scope="module")
def seed_record():
    return load_model("seed").simulate(30000, seed=21)


def test_lesson_case_finds_colored_actuator_noise_in_place_of_white(seed_record):
    """Against the lesson's nominal model, the first effect is the AR(1) actuator noise that the
    nominal model treats as white; its std is recovered within its 95 % interval and 30 %."""
    rec = seed_record
    rep = diagnose(load_model("seed-nominal"), rec.t, rec.y, rec.u, max_effects=1)
    first = rep["missing"][0]
    assert first["effect"] == "actuator.ar1" and first["mode"] == "replace:actuator.white"
    lo, hi = first["interval"]["std"]
    assert lo <= 0.08 <= hi and abs(first["params"]["std"] / 0.08 - 1) < 0.3
    assert rep["error_after"] < rep["error_before"] / 100


def test_nothing_reported_when_the_model_is_right(seed_record):
    rec = seed_record
    rep = diagnose(load_model("seed"), rec.t, rec.y, rec.u, max_effects=1)
    assert rep["missing"] == []
    assert max(c["score"] for c in rep["candidates"]) < 10


def test_quantization_grid_detected():
    step = 0.001
    y = step * np.round(np.random.default_rng(1).normal(0, 0.01, (5000, 1)) / step)
    assert quantization_grid(y) == [pytest.approx(step, rel=1e-9)]
    assert quantization_grid(np.random.default_rng(2).normal(0, 1, (5000, 1))) == [None]
