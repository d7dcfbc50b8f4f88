"""The package's import structure: a graph without cycles, the command line at its top, and a
command line that starts without the heavy libraries.

The graph is read from the source (``ast``), not from an interpreter's ``sys.modules``: every
``import`` and ``from ... import`` of every module of ``service`` and ``viewers``, at the top level
and inside functions alike. An import inside a function still ties the two modules together (it
runs whenever the function does); deferring it hides a cycle from the interpreter, not from a
reader. An edge goes to the module named (``from pkg import sub`` to ``pkg.sub`` when ``sub`` is a
module, else to ``pkg``, whose ``__init__`` holds the name).

The start-up check runs in a fresh interpreter, so no other test's imports count, and asserts on
the modules loaded, not on time (no test depends on the machine's speed).
"""

from __future__ import annotations

import ast
import functools
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
# source folder -> the package it installs as (pyproject.toml's package-dir)
PACKAGES = {"service": "noiselab", "viewers": "noiselab.viewers"}
# modules below the command line: none of them imports it (the CLI imports them)
BELOW_CLI = ("noiselab.nodes", "noiselab.diagnose", "noiselab.model", "noiselab.stats", "noiselab.commands",
             "noiselab.recordings", "noiselab.wire", "noiselab.viewers")
# the recordings (and the wire contract they are written in) sit below these: none of them is imported by them
ABOVE_RECORDINGS = ("noiselab.diagnose", "noiselab.nodes", "noiselab.commands", "noiselab.cli", "noiselab.demo",
                    "noiselab.viewers")
# third-party libraries a command loads when it runs, never to read its flags
HEAVY = ("numpy", "scipy", "zenoh", "mcap", "rerun", "matplotlib", "rosbags")


def _modules() -> dict[str, Path]:
    """Dotted module name -> source file, for every module of the packages."""
    mods = {}
    for folder, pkg in PACKAGES.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            parts = (pkg, *path.relative_to(ROOT / folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            mods[".".join(parts)] = path
    return mods


def test_the_installed_packages_are_every_folder_of_the_source():
    """pyproject.toml lists the packages by their installed names (setuptools cannot find renamed
    packages): the list must be exactly the source folders that hold an ``__init__.py``, so a new
    subpackage is not left out of a wheel."""
    import tomllib
    listed = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]
    folders = sorted(m for m, path in _modules().items() if path.name == "__init__.py")
    assert sorted(listed) == folders


def _resolve(node: ast.ImportFrom, module: str, is_pkg: bool) -> str:
    """The absolute name of ``from <node.module> import ...`` written in ``module``."""
    if not node.level:
        return node.module or ""
    base = module.split(".") if is_pkg else module.split(".")[:-1]
    base = base[:len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


@functools.cache
def import_graph() -> dict[str, set[str]]:
    """module -> the package modules it imports (module docstring); read once, not to be changed."""
    mods = _modules()
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for mod, path in mods.items():
        is_pkg = path.name == "__init__.py"
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = _resolve(node, mod, is_pkg)
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base for a in node.names]
            for t in targets:
                while t and t not in mods:          # `import a.b.c` of a name inside a module: its module
                    t = t.rpartition(".")[0]
                if t and t != mod:
                    graph[mod].add(t)
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` as a list of modules (first == last), or None (depth-first search)."""
    state: dict[str, int] = {}               # 1: on the current path, 2: done
    path: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        path.append(m)
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                return path[path.index(n):] + [n]
            if n not in state:
                found = visit(n)
                if found:
                    return found
        state[m] = 2
        path.pop()
        return None

    for m in sorted(graph):
        if m not in state:
            found = visit(m)
            if found:
                return found
    return None


def test_the_graph_sees_imports_inside_functions():
    """The walk finds a deferred import (the run command imports the runner inside its function)."""
    graph = import_graph()
    assert "noiselab.nodes.runner" in graph["noiselab.commands.run"]
    assert "noiselab.errors" in graph["noiselab.commands.allan"]


def test_the_package_has_no_import_cycle():
    cycle = find_cycle(import_graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_nothing_below_the_command_line_imports_it():
    graph = import_graph()
    offenders = sorted(m for m, deps in graph.items()
                       if m.startswith(BELOW_CLI) and any(d == "noiselab.cli" for d in deps))
    assert offenders == [], offenders


def test_the_recordings_sit_below_the_analysis_and_the_nodes():
    """Reading, writing and salvaging recordings and turning one into a series
    (``noiselab.recordings``, in the wire contract ``noiselab.wire``) import neither the analysis,
    the diagnosis, a node, a command nor the CLI: those take a series, never a file."""
    graph = import_graph()
    lower = sorted(m for m in graph if m == "noiselab.wire" or m.startswith("noiselab.recordings."))
    assert "noiselab.recordings.reader" in lower and "noiselab.wire" in graph["noiselab.recordings.reader"]
    offenders = sorted((m, d) for m in lower for d in graph[m] if d.startswith(ABOVE_RECORDINGS))
    assert offenders == [], offenders


def test_the_command_line_builds_its_parser_without_the_heavy_libraries():
    """``noiselab --help`` and the parsing of any command's flags: the CLI and every command
    module (``noiselab.commands``, registered at parser-build time) import what a command needs
    when it runs, so reading the flags loads none of the numeric, transport, file-format or
    plotting libraries."""
    code = ("import json, sys\n"
            "import noiselab.cli\n"
            "noiselab.cli.build_parser()\n"
            f"heavy = {HEAVY!r}\n"
            "print(json.dumps(sorted({m.split('.')[0] for m in sys.modules} & set(heavy))))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120,
                       check=False)
    assert r.returncode == 0, r.stderr[-2000:]
    assert json.loads(r.stdout.strip().splitlines()[-1]) == []


def test_help_prints_without_the_heavy_libraries():
    """``noiselab --help`` as a user runs it (the module entry point): the usage, exit 0, and no
    heavy library loaded by the time the interpreter exits."""
    code = ("import atexit, json, sys\n"
            f"heavy = {HEAVY!r}\n"
            "atexit.register(lambda: sys.stderr.write('LOADED ' + json.dumps(sorted({m.split('.')[0] for m in "
            "sys.modules} & set(heavy))) + '\\n'))\n"
            "sys.argv = ['noiselab', '--help']\n"
            "from noiselab.cli import main\n"
            "sys.exit(main())\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120,
                       check=False)
    assert r.returncode == 0 and r.stdout.startswith("usage: noiselab"), (r.returncode, r.stdout[:500], r.stderr[-2000:])
    loaded = [line for line in r.stderr.splitlines() if line.startswith("LOADED ")]
    assert loaded and json.loads(loaded[-1][len("LOADED "):]) == [], r.stderr[-2000:]
