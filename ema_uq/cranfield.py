"""The Cranfield study lives in :mod:`ema_uq.rigs.cranfield`; this name stays for code that
imports it from here (the same module object, private names and all)."""
import sys

from .rigs import cranfield

sys.modules[__name__] = cranfield
