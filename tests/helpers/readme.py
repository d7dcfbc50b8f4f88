"""The README's code blocks, and its main command run as a user would (once per test run)."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

from helpers.once import run_once

ROOT = Path(__file__).resolve().parents[2]
README = (ROOT / "README.md").read_text()


def readme_blocks(lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", README, flags=re.S)


def main_command_steps() -> list[str]:
    """The noiselab steps of the README's main command (its venv/pip steps are what CI itself runs)."""
    first = readme_blocks("sh")[0].strip()
    steps = [s.strip() for s in first.split("&&")]
    return [s.replace(".venv/bin/noiselab", "noiselab") for s in steps if ".venv/bin/noiselab" in s]


def run_noiselab(cmd: str, cwd: Path):
    """A README line ``noiselab ...`` run as ``python -m noiselab.cli ...`` in ``cwd``, its words
    split as a POSIX shell splits them (quotes keep a field path's ``*`` from the shell's glob)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "noiselab.cli", *shlex.split(cmd)[1:]], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=900)


def readme_main_command(tmp_path_factory):
    """The README's main command (``noiselab demo`` with its defaults), run once per
    test run in one directory: (the directory, [{cmd, returncode, stdout, stderr}] per step, up to
    the first that fails). test_readme checks the run as a user sees it, test_demo what it wrote."""
    def make(d: Path) -> list[dict]:
        (d / "service").symlink_to(ROOT / "service")       # README paths like service/scenarios/...
        runs = []
        for cmd in main_command_steps():
            res = run_noiselab(cmd, d)
            runs.append({"cmd": cmd, "returncode": res.returncode, "stdout": res.stdout, "stderr": res.stderr})
            if res.returncode:
                break
        return runs

    return run_once(tmp_path_factory, "readme-main", make)
