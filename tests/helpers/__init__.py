"""Helpers shared by test modules in several folders, one concept per module; a test module
imports them explicitly (``from helpers.live import ...``) and never imports another test module.

- ``processes``: a child process whose output lines a test waits on (the ``spawn`` fixture's).
- ``once``: a machine-wide lock, and work done once per test run whichever xdist worker asks.
- ``cli``: ``noiselab`` run in this process, and the one-line bad-input check.
- ``readme``: the README's code blocks and its main command, run once per test run.
- ``models``: model files used by tests in several folders.
- ``recordings``: MCAP recordings written for a test (noiselab's own, and foreign ones).
- ``rrd``: an ``.rrd`` file read back.
- ``live``: the live pipeline's checks (Zenoh sessions on loopback, what a recording must hold).
- ``allan_reference``: published and Stable32 reference values for the Allan deviations.
"""
