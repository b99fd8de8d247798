"""The EMPS benchmark lives in :mod:`ema_uq.rigs.emps`; this name stays for code that imports
it from here (the same module object, private names and all)."""
import sys

from .rigs import emps

sys.modules[__name__] = emps
