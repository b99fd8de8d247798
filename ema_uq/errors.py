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


class InputFileError(EmaUqError):
    """A file that cannot be opened, read or written as asked: missing, a directory, or
    without permission (the operating system's error, turned into a user error where the
    package touches the file system)."""


#: operating-system errors that name a path the user gave, not a fault of the package
FILE_ACCESS_ERRORS = (FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError, FileExistsError)


class ReportError(EmaUqError):
    """A figure or report asked of a result file that does not hold it (a parameter that was
    not sampled, a posterior without predictive draws, a result without profiles)."""
