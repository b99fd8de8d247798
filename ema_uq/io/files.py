"""What every reader and writer of :mod:`ema_uq.io` shares: :class:`DataFileError`, the
measurement formats, checks of provenance attributes, and output paths checked before a
long computation and written atomically."""
from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..errors import EmaUqError

#: Measurement file formats by file extension.
FORMATS = {".nc": "netcdf", ".csv": "csv"}
TIME_UNIT = "s"
# Attribute names the writer owns; provenance attrs may not use them.
_RESERVED = ("concept", "experiment", "units")
_VERSION_KEY = "ema_uq_version"
_ATTR_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-]*$")
_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
_NETCDF3_MAGIC = b"CDF"


class DataFileError(EmaUqError):
    """A data or result file that cannot be read, written or does not meet the file contract."""


# --------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------
def _one_line(text: object) -> str:
    return " ".join(str(text).split())


def _fail(path: Path, problem: str) -> DataFileError:
    return DataFileError(f"file {path}: {_one_line(problem)}")


def data_format(path: str | os.PathLike) -> str:
    """``"netcdf"`` or ``"csv"`` from the file extension; anything else is a :class:`DataFileError`."""
    path = Path(path)
    fmt = FORMATS.get(path.suffix.lower())
    if fmt is None:
        raise DataFileError(
            f"file {path}: unknown file extension {path.suffix or '(none)'!r}; "
            f"name measurement files *.nc (NetCDF) or *.csv"
        )
    return fmt


def _normalize_unit(unit: str) -> str:
    u = "".join(str(unit).replace("·", " ").replace("*", " ").split())
    return {"seconds": "s", "second": "s", "sec": "s", "": "1", "-": "1"}.get(u, u)


def _python_value(value: Any) -> Any:
    """numpy scalars/arrays (as returned by NetCDF attribute reads) to plain Python."""
    if isinstance(value, np.ndarray):
        return value.item() if value.ndim == 0 else value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, bytes):
        return value.decode("utf-8", errors="replace")
    return value


def _attr_kind(value: Any) -> type | None:
    if isinstance(value, str):
        return str
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return float
    return None


def _check_attrs(path: Path, attrs: Mapping[str, Any]) -> dict[str, Any]:
    """Provenance attributes that both formats can store: str, bool (stored as 0/1), int,
    float or a flat list of numbers or strings."""
    out: dict[str, Any] = {}
    for key, value in attrs.items():
        if not isinstance(key, str) or not _ATTR_NAME.match(key):
            raise _fail(path, f"attribute name {key!r} is not valid; use letters, digits, '_', '.', '-'")
        if key in _RESERVED:
            raise _fail(path, f"attribute {key!r} is reserved for the file layout; rename it in measurement.attrs")
        value = _python_value(value)
        if isinstance(value, bool):
            value = int(value)  # NetCDF has no boolean attribute type
        elif isinstance(value, (list, tuple)):
            value = [_python_value(v) for v in value]
            kinds = {_attr_kind(v) for v in value}
            if not value or None in kinds or len(kinds) > 1:
                raise _fail(path, f"attribute {key!r} = {value!r} cannot be stored; "
                                  "use a non-empty list of only numbers or only strings")
        elif not isinstance(value, (str, int, float)):
            raise _fail(path, f"attribute {key!r} has type {type(value).__name__}; "
                              "store str, int, float, bool or a flat list of numbers or strings")
        out[key] = value
    return out


def prepare_output(path: str | os.PathLike, *, measurement: bool = False) -> Path:
    """Check that ``path`` can be written (creating its parent directories) before any
    long computation; with ``measurement=True`` also that its extension is .nc or .csv."""
    path = Path(path)
    if measurement:
        data_format(path)
    blocker = next((p for p in (path.parent, *path.parent.parents) if p.exists()), None)
    if blocker is not None and not blocker.is_dir():
        raise _fail(path, f"{blocker} is a file, not a directory; choose another output location")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise _fail(path, f"cannot create the directory {path.parent} ({exc.strerror or exc}); "
                          "choose a writable output location") from None
    if path.is_dir():
        raise _fail(path, "this is a directory; give a file name")
    if not os.access(path.parent, os.W_OK | os.X_OK):
        raise _fail(path, f"the directory {path.parent} is not writable; choose a writable output location")
    return path


def _atomic_write(path: Path, write) -> None:
    """Write through a temporary sibling file and rename, so a failed or interrupted write
    never leaves a truncated file that a workflow would take for a finished result."""
    prepare_output(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        write(tmp)
        os.replace(tmp, path)
    except OSError as exc:
        raise _fail(path, f"cannot write the file ({exc.strerror or exc}); choose a writable output location") from None
    finally:
        if tmp.exists():
            tmp.unlink()


def repository_root() -> Path:
    """The folder holding the package directory (the repository root of an editable install)."""
    return Path(__file__).resolve().parents[2]
