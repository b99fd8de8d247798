"""The root of every error that the user can mend: :class:`EmaUqError`.

Each part of the package names its own failures (``DataFileError``, ``ParameterError``,
``IdentificationError``, ...); all of them derive from :class:`EmaUqError`, so the command
line tells a bad input (one line ``ema-uq: error: ...``, exit 2) from a fault of the package
(its traceback and a request to report it). An exception of any other class that escapes a
verb is such a fault.

:class:`EmaUqError` derives from ``ValueError``, so code that caught ``ValueError`` around a
package call before this root existed keeps working.
"""
from __future__ import annotations


class EmaUqError(ValueError):
    """Input that the package cannot use: a bad value, file, study or setting. The message
    says what is wrong and, where it can, how to mend it."""


#: operating-system errors about a path the user gave, not a fault of the package. The readers
#: and writers of :mod:`ema_uq.io` turn them into ``DataFileError`` with the fix; the command
#: line reports any that escape elsewhere (a figure path, a study file) as a user error too.
FILE_ACCESS_ERRORS = (FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError, FileExistsError)


class ReportError(EmaUqError):
    """A figure or report asked of a result file that does not hold it (a parameter that was
    not sampled, a posterior without predictive draws, a result without profiles)."""
