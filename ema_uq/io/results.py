"""JSON result files: numpy values and non-finite floats converted, written atomically, read
with one-line errors."""
from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from .files import _atomic_write, _fail


# --------------------------------------------------------------------------------------
# JSON result files
# --------------------------------------------------------------------------------------
def _jsonable(obj: Any) -> Any:
    """Plain JSON types; numpy scalars/arrays become numbers/lists, non-finite floats null
    (strict JSON has no NaN, and result files are read by tools other than Python)."""
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return _jsonable(obj.item())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if obj is None or isinstance(obj, (str, int, float, bool)):
        return obj
    raise TypeError(f"cannot store a {type(obj).__name__} in JSON; convert it to numbers, strings, lists or dicts")


def write_json(path: str | os.PathLike, obj: Any) -> Path:
    """Write ``obj`` as indented JSON (numpy values converted, NaN/inf -> null), creating
    parent directories; the write is atomic. Returns the path."""
    path = Path(path)
    try:
        text = json.dumps(_jsonable(obj), indent=2, allow_nan=False) + "\n"
    except TypeError as exc:
        raise _fail(path, str(exc)) from None

    def write(tmp: Path) -> None:
        tmp.write_text(text, encoding="utf-8")

    _atomic_write(path, write)
    return path


def read_json(path: str | os.PathLike) -> Any:
    """Read a JSON file; a missing, unreadable or malformed file is a :class:`DataFileError`."""
    path = Path(path)
    if not path.is_file():
        raise _fail(path, "no such file; check the path or run the step that writes it")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise _fail(path, f"cannot read the file ({exc}); check its permissions and encoding") from None
    except json.JSONDecodeError as exc:
        raise _fail(path, f"not valid JSON ({exc.msg} at line {exc.lineno}, column {exc.colno}); "
                          "repair the file or write it again") from None


# --------------------------------------------------------------------------------------
# Snakemake benchmark files
# --------------------------------------------------------------------------------------
def read_benchmark(path: str | os.PathLike) -> dict[str, float] | None:
    """The last record of a Snakemake benchmark file (tab-separated, a header line): wall time
    ``s`` [s], ``cpu_s`` [s] (NaN when this Snakemake version does not measure it) and
    ``max_rss`` [MB]. None for a file still being written or of a format without them: a cost
    table skips such a job rather than failing a report."""
    lines = [line.split("\t") for line in Path(path).read_text(encoding="utf-8").splitlines() if line.strip()]
    if len(lines) < 2:
        return None
    record = dict(zip(lines[0], lines[-1]))
    try:
        wall, rss = float(record["s"]), float(record["max_rss"])
    except (KeyError, ValueError):
        return None
    try:
        cpu = float(record.get("cpu_time", "nan"))
    except ValueError:                  # "NA": not measured
        cpu = math.nan
    return {"s": wall, "cpu_s": cpu, "max_rss": rss}
