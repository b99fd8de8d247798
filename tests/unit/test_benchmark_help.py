"""Every benchmark script answers ``--help`` with its usage and exits 0 without running its
campaign (a help text with a bare ``%`` made argparse raise instead; a script without a parser
ran its whole campaign). The scripts run in one child process: some set environment variables
(numba's thread count, a record folder) as they start, which must not reach the other tests."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"

DRIVER = r"""
import contextlib, io, json, runpy, sys
answers = {}
for script in sys.argv[1:]:
    sys.argv, out = [script, "--help"], io.StringIO()
    try:
        with contextlib.redirect_stdout(out):
            runpy.run_path(script, run_name="__main__")
        code = "ran without stopping"
    except SystemExit as stop:
        code = stop.code
    except Exception as exc:
        code = f"{type(exc).__name__}: {exc}"
    answers[script] = [code, out.getvalue()[:6]]
print(json.dumps(answers))
"""


def test_every_benchmark_script_prints_its_usage_for_help():
    scripts = sorted(str(p) for p in BENCHMARKS.glob("*.py"))
    assert len(scripts) >= 10
    done = subprocess.run([sys.executable, "-c", DRIVER, *scripts], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    answers = json.loads(done.stdout.strip().splitlines()[-1])
    wrong = {Path(s).name: a for s, a in answers.items() if a != [0, "usage:"]}
    assert not wrong, wrong
