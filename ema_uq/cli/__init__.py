"""The ``ema-uq`` command line (also ``python -m ema_uq``); contract in docs/INTERFACES.md.

One room per group of verbs (:mod:`.estimation`: simulate, identify, sample, sbc;
:mod:`.analysis`: sensitivity, identifiability; :mod:`.diagnosis`: gap, gap-selfcheck,
fault-diagnosis; :mod:`.reporting`: report, screenshot, check-study, compile), each verb an
``add_<verb>(subparsers)`` that registers its parser and binds a ``_run_<verb>(args) -> str``
handler. Handlers only translate arguments into package calls and files; the numerics live
in the package. What the verbs share is in :mod:`.arguments`; the parser assembly, the study
settings and the exit statuses are in :mod:`.app`. Adding a verb means writing that pair in
its group and listing the register function in :data:`VERBS`.
"""
from .app import BUG_REPORT, EXIT_BUG, EXIT_ERROR, EXIT_OK, SIMULATING_VERBS, VERBS, build_parser, main
from .app import _apply_study, _given_options  # noqa: F401 - the tests lay a study under parsed options
from .arguments import CONCEPTS, EXPERIMENT_NAMES, PROG, UNIDENTIFIABLE_MODES, CLIError

__all__ = ["BUG_REPORT", "CONCEPTS", "EXIT_BUG", "EXIT_ERROR", "EXIT_OK", "EXPERIMENT_NAMES", "PROG",
           "SIMULATING_VERBS", "UNIDENTIFIABLE_MODES", "VERBS", "CLIError", "build_parser", "main"]
