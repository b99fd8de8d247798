"""The Cranfield baseline lives in :mod:`ema_uq.rigs.cranfield_baseline`; this name stays for code
that imports it from here (the same module object)."""
import sys

from .rigs import cranfield_baseline

sys.modules[__name__] = cranfield_baseline
