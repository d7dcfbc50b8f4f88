"""Every example in the README runs (STYLE 12): the `console` blocks, the Python block, and the
main command's noiselab steps (the venv/pip steps are what CI itself runs)."""

import os
import re
import subprocess
import sys

import pytest

from helpers.readme import ROOT, main_command_steps, readme_main_command, run_noiselab
from helpers.readme import readme_blocks as blocks


def console_commands():
    return [line.strip() for b in blocks("console") for line in b.splitlines() if line.strip().startswith("noiselab ")]


def console_blocks():
    return [[ln.strip() for ln in b.splitlines() if ln.strip().startswith("noiselab ")] for b in blocks("console")]


@pytest.fixture()
def scratch(tmp_path):
    (tmp_path / "service").symlink_to(ROOT / "service")   # README paths like service/scenarios/...
    return tmp_path


def test_readme_has_examples():
    assert len(console_commands()) >= 5
    assert main_command_steps(), "the README's main command must run noiselab"
    test_cmd = blocks("sh")[1].strip()
    ci = (ROOT / ".ci" / "run").read_text()
    assert test_cmd.split("&&")[-1].strip() in ci, "CI must run the README's test command"


@pytest.mark.slow
@pytest.mark.parametrize("block", console_blocks(), ids=lambda b: b[0][:40])
def test_console_examples(block, scratch):
    """Each console block runs in order in one directory (later lines use earlier outputs)."""
    for cmd in block:
        res = run_noiselab(cmd, scratch)
        assert res.returncode == 0, (cmd, res.stderr)
        assert res.stdout.strip()
        for out in re.findall(r"--(?:out|rrd) (\S+)", cmd):
            target = scratch / out
            assert target.exists() and (target.is_dir() or target.stat().st_size > 0), out


@pytest.mark.slow
def test_main_command_steps(tmp_path_factory):
    """The main command as a user runs it, from a fresh directory (run once per test run: test_demo
    checks what it wrote)."""
    d, runs = readme_main_command(tmp_path_factory)
    for r in runs:
        assert r["returncode"] == 0, (r["cmd"], r["stderr"])
    assert [r["cmd"] for r in runs] == main_command_steps()
    rec = d / "recordings"
    for name in ("demo-seed.mcap", "demo-seed.rrd", "demo-seed.png", "demo-seed-diagnosis.rrd",
                 "demo-seed-diagnosis.png", "demo-seed-fitted.toml", "demo-seed-summary.json"):
        assert (rec / name).stat().st_size > 0, name
    out = runs[-1]["stdout"]
    assert "the lesson's check" in out and "x off" in out and "model error" in out, out


def test_python_example(scratch):
    code = blocks("python")[0]
    res = subprocess.run([sys.executable, "-c", code], cwd=scratch, env=dict(os.environ, PYTHONPATH=str(ROOT)),
                         capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, res.stderr


def _port_free(port: int) -> bool:
    import socket
    with socket.socket() as s:
        # as the listener will (Rust's TcpListener sets it): a connection of an earlier test in
        # TIME_WAIT on the port does not make it busy; a listener on it does
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


@pytest.mark.slow
def test_three_terminal_example(default_endpoint, scratch):
    """The by-hand example, as written, on the default endpoint: the recorder is started first and
    waits for the emulator; Ctrl-C (SIGINT) finishes its file; the replay republishes it."""
    import signal
    if not _port_free(7447):
        pytest.skip("the example uses the default endpoint tcp/127.0.0.1:7447, which is in use here")
    lines = [ln.split("#")[0].strip() for ln in blocks("sh")[2].strip().splitlines()]
    assert [ln.split()[1] for ln in lines] == ["record", "emulate", "replay"]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    (scratch / "recordings").mkdir()
    rec = subprocess.Popen([sys.executable, "-m", "noiselab.cli", *lines[0].split()[1:]], cwd=scratch, env=env,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        res = run_noiselab(lines[1], scratch)
        assert res.returncode == 0, res.stderr
        rec.send_signal(signal.SIGINT)
        out, err = rec.communicate(timeout=60)
        assert rec.returncode == 0, err
        assert "500 messages" in out and "no gaps" in out, out
        res = run_noiselab(lines[2], scratch)
        assert res.returncode == 0, res.stderr
        assert "replayed" in res.stdout
    finally:
        if rec.poll() is None:
            rec.kill()
            rec.wait()
