"""``noiselab`` run in the test's own process, and the check that bad input is one line, exit 2."""

from __future__ import annotations


def cli_in_process(capsys, *argv) -> tuple[int, str, str]:
    """``noiselab ARGV`` in this process: (exit code, stdout, stderr). argparse's own errors exit
    through SystemExit; anything else raised is a traceback and fails the test."""
    from noiselab.cli import main
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as exc:
        rc = exc.code
    out, err = capsys.readouterr()
    return rc, out, err


def assert_bad(result, *parts: str) -> str:
    """Exit 2 and one line on stderr, ``noiselab: ...``, no traceback, holding every one of
    ``parts``; the line is returned."""
    rc, out, err = result
    assert rc == 2, (rc, out, err[-3000:])
    lines = err.splitlines()
    assert len(lines) == 1 and err.endswith("\n") and lines[0].startswith("noiselab: "), err[-3000:]
    assert "Traceback" not in err, err[-3000:]
    for part in parts:
        assert part in lines[0], (part, lines[0])
    return lines[0]
