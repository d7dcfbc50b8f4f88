"""Every example in the README runs (STYLE 12): the `console` blocks, the Python block, and the
main command's noiselab steps (the venv/pip steps are what CI itself runs)."""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def blocks(lang):
    return re.findall(rf"```{lang}\n(.*?)```", README, flags=re.S)


def console_commands():
    return [line.strip() for b in blocks("console") for line in b.splitlines() if line.strip().startswith("noiselab ")]


def main_command_steps():
    first = blocks("sh")[0].strip()
    steps = [s.strip() for s in first.split("&&")]
    return [s.replace(".venv/bin/noiselab", "noiselab") for s in steps if ".venv/bin/noiselab" in s]


def run_noiselab(cmd: str, cwd: Path):
    args = cmd.split()[1:]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "service.cli", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=300)


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


@pytest.mark.parametrize("cmd", console_commands())
def test_console_example(cmd, scratch):
    res = run_noiselab(cmd, scratch)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip()
    for out in re.findall(r"--out (\S+)", cmd):
        assert (scratch / out).stat().st_size > 0


def test_main_command_steps(scratch):
    for cmd in main_command_steps():
        res = run_noiselab(cmd, scratch)
        assert res.returncode == 0, (cmd, res.stderr)
    assert (scratch / "recordings" / "seed.mcap").stat().st_size > 0


def test_python_example(scratch):
    code = blocks("python")[0]
    res = subprocess.run([sys.executable, "-c", code], cwd=scratch, env=dict(os.environ, PYTHONPATH=str(ROOT)),
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
