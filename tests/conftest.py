"""Make ``tests/`` importable so tests and benchmarks can ``import reference_scipy``."""
import os
import sys

_HERE = os.path.dirname(os.path.abspath(__file__))
if _HERE not in sys.path:
    sys.path.insert(0, _HERE)
