"""Progress on stderr (noiselab.progress) for the commands that run for tens of seconds: shown at a
terminal, never on stdout, never with --json, never when stderr is not a terminal unless
--progress forces it.

The commands run as real processes whose stderr is a pseudo-terminal (python's pty module) or a
pipe; what they wrote is read whole after they exit. Nothing here depends on the machine's speed:
a phase's bar is drawn when the phase begins, whatever its length.
"""

from __future__ import annotations

import fcntl
import json
import os
import pty
import re
import struct
import subprocess
import sys
import termios
import threading
from pathlib import Path

import pytest

from noiselab import parallel
from noiselab.model import load_model
from noiselab.progress import Progress, Steps, wanted
from noiselab.recordings.simulated import write_simulation

ROOT = Path(__file__).resolve().parents[2]
T_RUN = 300                  # an upper bound on a command's run: a test never passes on it


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    """30 s of the seed lesson (Ts = 10 ms), from which seed-nominal lacks effects."""
    path = tmp_path_factory.mktemp("progress") / "seed.mcap"
    write_simulation(load_model("seed"), 3000, 1, path)
    return path


def run_on_pty(args: list[str], cols: int | None = 120) -> tuple[int, str, str]:
    """``python -m noiselab.cli ARGS`` with stderr on a pseudo-terminal (``cols`` x 40, or left
    unsized: 0 x 0) and stdout on a pipe: (exit code, stdout, what the terminal received)."""
    master, slave = pty.openpty()
    if cols is not None:
        fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 40, cols, 0, 0))
    got = []

    def drain():
        while True:
            try:
                chunk = os.read(master, 65536)
            except OSError:                    # EIO: every writer of the terminal has closed it
                return
            if not chunk:
                return
            got.append(chunk)

    reader = threading.Thread(target=drain)
    try:
        proc = subprocess.Popen([sys.executable, "-m", "noiselab.cli", *args], stdout=subprocess.PIPE,
                                stderr=slave, stdin=subprocess.DEVNULL, cwd=ROOT)
    finally:
        os.close(slave)
    reader.start()
    try:
        out, _ = proc.communicate(timeout=T_RUN)
    finally:
        proc.kill()
        reader.join(T_RUN)
        os.close(master)
    return proc.returncode, out.decode(), b"".join(got).decode(errors="replace")


def os_thread_count() -> int:
    """The threads of this process as the kernel counts them (0 where /proc cannot tell)."""
    try:
        return len(os.listdir("/proc/self/task"))
    except OSError:
        return 0


def run_on_pipe(args: list[str]) -> subprocess.CompletedProcess:
    """The command with stdout and stderr on pipes (text: a bar's carriage returns read as newlines)."""
    return subprocess.run([sys.executable, "-m", "noiselab.cli", *args], capture_output=True, text=True,
                          cwd=ROOT, timeout=T_RUN, check=False)


# ------------------------------------------------------------------------------- the class


def test_wanted_is_off_with_json_forced_with_progress_else_the_terminal_decides():
    assert wanted(force=False, json_output=True) is False
    assert wanted(force=True, json_output=True) is False
    assert wanted(force=True) is True
    assert wanted() is None


def test_a_bar_counts_from_worker_threads_and_starts_no_thread(tmp_path, monkeypatch):
    """8 threads advancing one bar 500 times each: 4000, none lost; the bar runs no thread of its
    own (tqdm's monitor is off), so a process that could fork still can (parallel.can_fork)."""
    err = tmp_path / "stderr"
    with open(err, "w") as f:
        monkeypatch.setattr(sys, "stderr", f)
        threads_before, os_threads, fork_ok = threading.active_count(), os_thread_count(), parallel.can_fork()
        bar = Progress(4000, "counting", enabled=True, unit=" items", unit_scale=False)
        assert threading.active_count() == threads_before and os_thread_count() == os_threads
        assert parallel.can_fork() == fork_ok
        workers = [threading.Thread(target=lambda: [bar.advance() for _ in range(500)]) for _ in range(8)]
        for w in workers:
            w.start()
        for w in workers:
            w.join()
        assert bar.done == 4000
        bar.close()
    text = err.read_text()
    assert "counting" in text and "4000/4000" in text


@pytest.mark.skipif(not hasattr(os, "fork"), reason="fork")
def test_a_forked_child_does_not_draw_the_parents_bar(tmp_path, monkeypatch):
    """A bar's copy in a forked child (the diagnosis forks while a bar shows) ignores updates:
    what the file holds after the child updated and closed its copy is what the parent drew."""
    err = tmp_path / "stderr"
    with open(err, "w", buffering=1) as f:
        monkeypatch.setattr(sys, "stderr", f)
        bar = Progress(10, "parent's", enabled=True)
        bar.update(3)
        f.flush()
        drawn = err.read_text()
        pid = os.fork()
        if pid == 0:                                            # the child: update, close, leave
            try:
                bar.update(9)
                bar.close()
                f.flush()
            finally:
                os._exit(0)
        os.waitpid(pid, 0)
        assert err.read_text() == drawn
        bar.close()
    assert "10" in err.read_text()


def test_steps_show_each_phase_with_its_count(tmp_path, monkeypatch):
    err = tmp_path / "stderr"
    with open(err, "w") as f:
        monkeypatch.setattr(sys, "stderr", f)
        with Steps("noiselab test", True, unit=" fits") as steps:
            steps("reading x.mcap")
            steps("candidates", 0, 5)
            steps("candidates", 3, 5)
            steps("candidates", 5, 8)        # the phase learned of 3 more
            steps("candidates", 8)
    text = err.read_text()
    assert "noiselab test: reading x.mcap" in text
    assert "noiselab test: candidates" in text and "8/8" in text
    with open(err, "w") as f:
        monkeypatch.setattr(sys, "stderr", f)
        with Steps("noiselab test", False) as steps:
            steps("reading x.mcap")
            steps("candidates", 1, 5)
    assert err.read_text() == ""


# ------------------------------------------------------------------------ the commands


@pytest.mark.parametrize("cols", [120, None], ids=["sized", "unsized"])
def test_diagnose_at_a_terminal_shows_its_phases_and_counts(recording, cols):
    """diagnose with stderr on a terminal: the reading, the candidates of the step with their
    count, the intervals; the report on stdout, no bar in it. An unsized terminal (0 x 0) gets the
    bar too, not an empty line."""
    code, out, term = run_on_pty(["diagnose", str(recording), "--model", "seed-nominal", "--max-effects", "1"],
                                 cols=cols)
    assert code == 0, term
    assert "noiselab diagnose: reading seed.mcap" in term
    assert "noiselab diagnose: step 1/1: candidates" in term
    assert re.search(r"step 1/1: candidates: +\d+%\|.*\| \d+/\d+ ", term), term   # a count: done/total
    assert "noiselab diagnose: profile intervals" in term
    assert "\r" not in out and "noiselab diagnose:" not in out and "model error" in out


def test_analyze_at_a_terminal_shows_its_phases(recording):
    code, out, term = run_on_pty(["analyze", str(recording), "--model", "seed-nominal"])
    assert code == 0, term
    assert "noiselab analyze: reading seed.mcap" in term
    assert "noiselab analyze: comparing 3000 samples with seed-nominal" in term
    assert "\r" not in out and "model error" in out


@pytest.mark.parametrize("command", ["analyze", "diagnose"])
def test_json_at_a_terminal_is_pure_json_and_no_bar(recording, command):
    """--json with stderr on a terminal: stdout is one JSON document, the terminal gets no bar
    (--progress does not force one either)."""
    args = [command, str(recording), "--model", "seed-nominal", "--json", "--progress"]
    if command == "diagnose":
        args += ["--max-effects", "1"]
    code, out, term = run_on_pty(args)
    assert code == 0, term
    rep = json.loads(out)
    assert rep["samples"] == 3000
    assert "\r" not in term and f"noiselab {command}: reading" not in term


@pytest.mark.slow
@pytest.mark.parametrize("command", ["analyze", "diagnose"])
def test_no_bar_when_stderr_is_a_pipe_unless_forced(recording, command):
    args = [command, str(recording), "--model", "seed-nominal"] + (["--max-effects", "1"] if command == "diagnose" else [])
    r = run_on_pipe(args)
    assert r.returncode == 0, r.stderr
    assert f"noiselab {command}: reading" not in r.stderr
    forced = run_on_pipe([*args, "--progress"])
    assert forced.returncode == 0, forced.stderr
    assert f"noiselab {command}: reading seed.mcap" in forced.stderr
    assert forced.stdout == r.stdout                      # the report itself is the same
