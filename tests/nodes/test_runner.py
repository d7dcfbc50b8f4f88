"""`noiselab run`'s pipeline when the port a node was given is taken before it binds it.

:func:`noiselab.nodes.runner.free_port` learns a free port by binding and closing it; another
process on the machine may take the port before the recorder or the live analyzer binds it (seen
under a loaded parallel test run). The node then exits saying the address is in use, and the run
starts it again on a new port instead of failing.
"""

from __future__ import annotations

import socket

import pytest

from noiselab.nodes import runner
from noiselab.recordings.load import load_noiselab

GYRO = """
name = "taken"
[sampling]
Ts = 0.01
[outputs]
names = ["gyro_x"]
units = ["rad/s"]
[sensor.white]
std = 0.01
"""


@pytest.mark.slow
@pytest.mark.parametrize("analyze", [False, True], ids=["recorder", "recorder+analyzer"])
def test_a_node_whose_port_was_taken_is_started_again_on_another(tmp_path, monkeypatch, analyze):
    model = tmp_path / "taken.toml"
    model.write_text(GYRO)
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as holder:   # the port another process took
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        taken = holder.getsockname()[1]
        real = runner.free_port
        given = []

        def free_port():            # the first port each node is given is the taken one
            port = taken if len(given) < (2 if analyze else 1) else real()
            given.append(port)
            return port

        monkeypatch.setattr(runner, "free_port", free_port)
        rep = runner.run_pipeline(str(model), "taken", duration=1.0, seed=3, out_dir=tmp_path / "out",
                                  analyze=analyze, speed=4.0, out_name="run")
    assert given.count(taken) == (2 if analyze else 1) and len(given) == (4 if analyze else 2), given
    assert rep["endpoint"] != f"tcp/127.0.0.1:{taken}"
    series = load_noiselab(rep["recording"], truth=False, Ts=0.01)
    assert series.y.shape == (100, 1)
    if analyze:
        assert rep["analysis"] is not None and rep["analysis"]["received"] >= 100, rep["analysis"]   # the measurements
