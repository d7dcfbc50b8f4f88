"""Behaviour check for a restructuring: save the JSON reports of the generated hidden-effect cases
and of the README's JSON examples, and compare two such sets to a relative tolerance.

Run on demand (not by pytest)::

    .venv/bin/python tests/bench/golden.py save DIR [--cases 40]     # reports of this checkout
    .venv/bin/python tests/bench/golden.py compare DIR_A DIR_B [--rtol 1e-9]

``save`` writes one JSON file per generated case (``hidden_set.make_case(seed)``, diagnosed with
``diagnose()`` as ``bench_diagnose.py`` does) and one per README command that prints JSON (run
as a process, in order, in one scratch directory, so later commands read earlier outputs).
``compare`` walks both sets: every number must agree to ``rtol`` (relative, with an absolute floor
of ``rtol`` times the largest magnitude of that array), every string and key alike, except wall
times (``seconds``, ``*_s``) and file paths, which differ between runs.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "bench"))

# README commands that print JSON, with the commands they read from before them (README order)
README = [
    "predict seed --json",
    "predict seed-nominal --json",
    "predict service/scenarios/seed.toml --json",
    "simulate seed-nominal --duration 10 --seed 2 --out nominal.mcap --json",
    "simulate seed --duration 120 --seed 4 --out seed120.mcap",
    "analyze seed120.mcap --model seed --json",
    "analyze seed120.mcap --model seed-nominal --json",
    "simulate hidden/actuator.ar1 --duration 120 --seed 3 --out hidden-ar1.mcap",
    "diagnose hidden-ar1.mcap --model hidden/actuator.ar1-nominal --fit-out ar1-fitted.toml --json",
    "diagnose hidden-ar1.mcap --model ar1-fitted.toml --json",
    "simulate imu --duration 120 --seed 3 --format ros2 --out imu_bag",
    "allan imu_bag --measurement /imu/measurement:angular_velocity.x --json",
    ("diagnose imu_bag --measurement /imu/measurement:angular_velocity.*,linear_acceleration.* "
     "--model imu-nominal --fit-out imu-fitted.toml --json"),
    "predict motor --json",
    "simulate motor --duration 60 --seed 1 --out motor.mcap",
    "diagnose motor.mcap --model motor-nominal --json",
]

IGNORED = {"seconds", "path", "file", "recording", "out", "fit_out", "created", "start_time_ns"}


def _cli(args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    (cwd / "service").exists() or (cwd / "service").symlink_to(ROOT / "service")
    return subprocess.run([sys.executable, "-c", "import sys; from noiselab.cli import main; sys.exit(main())",
                           *args.split()], check=False, capture_output=True, text=True, env=env, cwd=cwd)


def save(out: Path, n_cases: int) -> None:
    from noiselab import one_blas_thread
    one_blas_thread()          # as bench_diagnose.py and the command line do
    from hidden_set import make_case

    from noiselab.diagnose.diagnose import diagnose
    from noiselab.diagnose.report import diagnosis_json
    from noiselab.model import parse_model

    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as d:
        for i, cmd in enumerate(README):
            r = _cli(cmd, Path(d))
            if r.returncode != 0:
                raise SystemExit(f"{cmd}: exit {r.returncode}: {r.stderr.strip()}")
            if cmd.endswith("--json"):
                (out / f"readme-{i:02d}.json").write_text(r.stdout)
            print(f"readme {i}: {cmd}", flush=True)
    for seed in range(n_cases):
        case = make_case(seed)
        truth, nominal = parse_model(case.truth, "truth"), parse_model(case.nominal, "nominal")
        rec = truth.simulate(round(case.duration / truth.Ts), seed=case.seed)
        rep = diagnose(nominal, rec.t, rec.y, rec.u)
        js = diagnosis_json(rep)
        js["fitted_model"] = rep["fitted_model"]
        (out / f"case-{seed:03d}.json").write_text(json.dumps(js))
        print(f"case {seed}: {[m['effect'] for m in rep['missing']]}", flush=True)


def _ignored(key) -> bool:
    return key in IGNORED or (isinstance(key, str) and key.endswith("_s") and key != "std_s"
                              and key != "tau_s")


def diff(a, b, where: str, rtol: float, out: list) -> None:
    """Append to ``out`` each place where ``a`` and ``b`` differ beyond ``rtol``."""
    if isinstance(a, dict) and isinstance(b, dict):
        if set(a) != set(b):
            out.append(f"{where}: keys {sorted(set(a) ^ set(b))}")
        for k in set(a) & set(b):
            if k == "fitted_model":         # a model file: compared as the table it writes
                diff(tomllib.loads(a[k]), tomllib.loads(b[k]), f"{where}.{k}", rtol, out)
            elif not _ignored(k):
                diff(a[k], b[k], f"{where}.{k}", rtol, out)
    elif isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            out.append(f"{where}: length {len(a)} vs {len(b)}")
            return
        scale = max((abs(x) for x in a if isinstance(x, (int, float)) and math.isfinite(x)), default=0.0)
        for i, (x, y) in enumerate(zip(a, b)):
            if isinstance(x, (int, float)) and isinstance(y, (int, float)) and not isinstance(x, bool):
                _num(x, y, f"{where}[{i}]", rtol, scale, out)
            else:
                diff(x, y, f"{where}[{i}]", rtol, out)
    elif isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
        _num(a, b, where, rtol, 0.0, out)
    elif isinstance(a, str) and isinstance(b, str) and a != b:
        # sentences carry numbers at 3 significant digits: compare them as words
        out.append(f"{where}: {a!r} vs {b!r}")
    elif type(a) is not type(b) or (not isinstance(a, (dict, list, str)) and a != b):
        out.append(f"{where}: {a!r} vs {b!r}")


def _num(x, y, where, rtol, scale, out) -> None:
    if math.isnan(x) and math.isnan(y) or x == y:
        return
    if abs(x - y) > rtol * max(abs(x), abs(y), scale):
        out.append(f"{where}: {x!r} vs {y!r}")


def compare(a: Path, b: Path, rtol: float) -> int:
    names = sorted(p.name for p in b.glob("*.json"))        # B may be a subset of A (fewer cases)
    bad = [f"not in {a}: {m}" for m in names if not (a / m).exists()]
    n = 0
    for name in names:
        if not (a / name).exists():
            continue
        n += 1
        out: list = []
        diff(json.loads((a / name).read_text()), json.loads((b / name).read_text()), name, rtol, out)
        bad += out
    print(f"{n} reports compared, {len(bad)} differences (rtol {rtol:g})")
    for line in bad[:200]:
        print("  " + line)
    return 1 if bad else 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="what", required=True)
    s = sub.add_parser("save")
    s.add_argument("dir", type=Path)
    s.add_argument("--cases", type=int, default=40)
    c = sub.add_parser("compare")
    c.add_argument("a", type=Path, help="the reference set")
    c.add_argument("b", type=Path, help="the set to check (may hold fewer cases)")
    c.add_argument("--rtol", type=float, default=1e-9)
    a = ap.parse_args(argv)
    if a.what == "save":
        save(a.dir, a.cases)
        return 0
    return compare(a.a, a.b, a.rtol)


if __name__ == "__main__":
    sys.exit(main())
