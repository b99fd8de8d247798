"""Reading and writing data files: measurements (NetCDF, CSV) and JSON result files.

This is the only module that touches files. Every reader validates what it reads against
the contract of docs/MODEL_SPEC.md ("Data files") and raises :class:`DataFileError` with a
one-line message naming the file, the problem and the fix.

Measured EMPS benchmark records (MATLAB ``.mat``, read-only) are read by :func:`read_emps`,
also through :func:`read_measurement`; :func:`emps_data_dir` / :func:`emps_files` locate them
outside the repository (``$EMA_UQ_EMPS_DIR``, the study key ``data.path`` or the default).
The Cranfield linear-actuator record sets (CSV, read-only) are read by :func:`read_cranfield`,
one measurement per (load, run) block, and located by :func:`cranfield_file`
(``$EMA_UQ_CRANFIELD_DIR``, the study key ``data.path`` or the default).

Measurement file layout
-----------------------
NetCDF (``.nc``, NetCDF4/HDF5 written through xarray's ``h5netcdf`` engine; classic
NetCDF3 files are read too):

- dimension and coordinate ``time`` [s], strictly increasing and uniform;
- input variables ``phi_r`` [rad], ``F_ER1`` [N], ``F_ER2`` [N] and optionally ``brake`` [1];
- any non-empty subset of the concept's output channels, named as ``Model.outputs``;
- every variable 1-D along ``time`` with a ``units`` attribute (absent = SI assumed);
- global attributes ``concept`` (``htls`` | ``lths``), ``experiment`` (profile name),
  ``ema_uq_version`` and the measurement's provenance attributes (``noise_fraction``,
  ``seed``, ``source``, ...).

CSV (``.csv``)::

    # concept = htls
    # units: time=s,phi_r=rad,F_ER1=N,F_ER2=N,Omega=rad/s,...
    # experiment = deploy-retract
    # noise_fraction = 0.02
    # source = simulated
    time,phi_r,F_ER1,F_ER2,Omega,...
    0,0,-2750,-2250,0,...

Comment values are JSON (so ``"0"`` stays a string and ``0`` an integer); a bare word
that is not JSON is read as a string, and the writer leaves such strings bare, so
headers read like ``# concept = htls``. Missing samples are written ``nan``; empty fields
and ``NaN``/``NA`` read as NaN. In both formats NaN marks a missing output sample and never
becomes zero.
"""
from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from .experiments import Experiment, ExperimentError, Measurement, check_time_grid
from .models import get_model
from .params import ParameterError

__all__ = [
    "DataFileError", "FORMATS", "data_format", "prepare_output", "write_measurement", "read_measurement",
    "write_json", "read_json", "read_emps", "emps_data_dir", "emps_files", "EMPS_DIR_ENV",
    "read_cranfield", "cranfield_data_dir", "cranfield_file", "CRANFIELD_DIR_ENV",
]

#: Measurement file formats by file extension.
FORMATS = {".nc": "netcdf", ".csv": "csv"}
TIME_UNIT = "s"
# Attribute names the writer owns; provenance attrs may not use them.
_RESERVED = ("concept", "experiment", "units")
_VERSION_KEY = "ema_uq_version"
_ATTR_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-]*$")
_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
_NETCDF3_MAGIC = b"CDF"


class DataFileError(ValueError):
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


# --------------------------------------------------------------------------------------
# writing
# --------------------------------------------------------------------------------------
def _layout(path: Path, measurement: Measurement):
    """(names, units, columns, global attrs) shared by both writers, time first."""
    from . import __version__

    model = measurement.model
    exp = measurement.experiment
    names = ["time"] + [k for k in model.inputs if k in exp.inputs] + list(measurement.channels)
    units = [TIME_UNIT] + [model.unit_of(k) for k in names[1:]]
    columns = [exp.time] + [exp.inputs[k] for k in model.inputs if k in exp.inputs] \
        + [measurement.values[:, i] for i in range(len(measurement.channels))]
    attrs = {"concept": measurement.concept, "experiment": exp.name}
    attrs.update(_check_attrs(path, {k: v for k, v in measurement.attrs.items() if k != _VERSION_KEY}))
    attrs[_VERSION_KEY] = __version__
    return names, units, columns, attrs


def write_measurement(path: str | os.PathLike, measurement: Measurement) -> Path:
    """Write ``measurement`` to ``path`` (``.nc`` or ``.csv``), creating parent directories.

    Time [s], inputs (SI) and the measurement's channels (units of ``Model.output_units``)
    are written as 1-D columns of ``n_samples`` float64 values; NaN samples stay NaN.
    The write is atomic: the file appears complete or not at all. Returns the path.
    """
    path = Path(path)
    fmt = data_format(path)
    names, units, columns, attrs = _layout(path, measurement)
    if fmt == "netcdf":
        import xarray as xr

        data_vars = {n: ("time", np.asarray(c, dtype=np.float64), {"units": u})
                     for n, c, u in zip(names[1:], columns[1:], units[1:])}
        ds = xr.Dataset(data_vars, coords={"time": ("time", columns[0], {"units": TIME_UNIT})}, attrs=attrs)
        encoding = {n: {"dtype": "float64", "_FillValue": np.nan} for n in names[1:]}
        # the time axis has no missing values, so it must not carry a fill value either
        encoding["time"] = {"dtype": "float64", "_FillValue": None}
        _atomic_write(path, lambda tmp: ds.to_netcdf(tmp, engine="h5netcdf", encoding=encoding))
    else:
        header = [f"# concept = {attrs.pop('concept')}",
                  "# units: " + ",".join(f"{n}={u}" for n, u in zip(names, units))]
        header += [f"# {k} = {_comment_value(v)}" for k, v in attrs.items()]
        table = np.column_stack(columns)

        def write(tmp: Path) -> None:
            with open(tmp, "w", encoding="utf-8", newline="\n") as fh:
                fh.write("\n".join(header) + "\n" + ",".join(names) + "\n")
                # 17 significant digits round-trip every float64 exactly
                np.savetxt(fh, table, delimiter=",", fmt="%.17g")

        _atomic_write(path, write)
    return path


# --------------------------------------------------------------------------------------
# reading
# --------------------------------------------------------------------------------------
def _parse_comment_value(text: str) -> Any:
    text = text.strip()
    try:
        return json.loads(text)
    except ValueError:
        return text


def _comment_value(value: Any) -> str:
    """JSON, except that a string which reads back unchanged is left bare (``source = simulated``)."""
    if (isinstance(value, str) and value.isprintable() and value == value.strip()
            and _parse_comment_value(value) == value):
        return value
    return json.dumps(value)


def _read_netcdf(path: Path) -> tuple[dict[str, np.ndarray], dict[str, str], dict[str, Any]]:
    import xarray as xr

    with open(path, "rb") as fh:
        magic = fh.read(8)
    if not magic:
        raise _fail(path, "the file is empty; write it again with 'ema-uq simulate' or a NetCDF writer")
    if magic.startswith(_HDF5_MAGIC):
        engine = "h5netcdf"
    elif magic.startswith(_NETCDF3_MAGIC):
        engine = "scipy"
    else:
        raise _fail(path, "not a NetCDF file (no NetCDF4/HDF5 or NetCDF3 signature); "
                          "give a NetCDF file or a .csv file with the matching extension")
    try:
        # raw times: "seconds" would otherwise be decoded into timedelta64
        ds = xr.load_dataset(path, engine=engine, decode_times=False, decode_timedelta=False)
    except Exception as exc:  # any reader failure is a malformed file to the user
        raise _fail(path, f"cannot read the NetCDF file ({type(exc).__name__}: {exc}); "
                          "check that the file is complete and not corrupted") from None
    if "time" not in ds.variables:
        raise _fail(path, "no 'time' variable; add a time coordinate in seconds")
    variables: dict[str, np.ndarray] = {}
    units: dict[str, str] = {}
    for name, var in ds.variables.items():
        name = str(name)
        if var.dims != ("time",):
            raise _fail(path, f"variable {name} has dimensions {tuple(map(str, var.dims))} and shape {var.shape}; "
                              "every variable must be 1-D along 'time'")
        if not (np.issubdtype(var.dtype, np.number) or var.dtype == bool):
            raise _fail(path, f"variable {name} holds {var.dtype} values; store numbers (float64)")
        variables[name] = np.asarray(var.values, dtype=float)
        if "units" in var.attrs:
            units[name] = str(_python_value(var.attrs["units"]))
    attrs = {str(k): _python_value(v) for k, v in ds.attrs.items()}
    return variables, units, attrs


def _read_csv(path: Path) -> tuple[dict[str, np.ndarray], dict[str, str], dict[str, Any]]:
    import pandas as pd

    try:
        # utf-8-sig: spreadsheet exports often start with a byte-order mark
        with open(path, "r", encoding="utf-8-sig") as fh:
            lines = fh.read().splitlines()
    except UnicodeDecodeError:
        raise _fail(path, "not a text CSV file (not UTF-8); give a comma-separated text file") from None
    if not any(line.strip() for line in lines):
        raise _fail(path, "the file is empty; it needs '# concept = ...', a header row and data rows")
    n_comments = 0
    attrs: dict[str, Any] = {}
    units: dict[str, str] = {}
    for line in lines:
        if not line.startswith("#"):
            break
        n_comments += 1
        body = line[1:].strip()
        if body.lower().startswith("units:"):
            for item in filter(None, (s.strip() for s in body[len("units:"):].split(","))):
                name, sep, unit = item.partition("=")
                if not sep:
                    raise _fail(path, f"cannot read the units entry {item!r}; write '# units: time=s,phi_r=rad,...'")
                units[name.strip()] = unit.strip()
        elif "=" in body:
            key, _, value = body.partition("=")
            attrs[key.strip()] = _parse_comment_value(value)
        # other comment lines are free text
    body_lines = lines[n_comments:]
    if not body_lines or not body_lines[0].strip():
        raise _fail(path, "no header row after the comment lines; add a row 'time,phi_r,F_ER1,F_ER2,...'")
    header = [h.strip().strip('"').strip() for h in body_lines[0].split(",")]
    duplicated = sorted({h for h in header if header.count(h) > 1})
    if duplicated:
        raise _fail(path, f"column(s) {', '.join(duplicated)} appear more than once in the header; keep one of each")
    if "" in header:
        raise _fail(path, "the header row has an empty column name; name every column")
    try:
        frame = pd.read_csv(path, skiprows=n_comments, header=0, names=header, dtype=float,
                            skipinitialspace=True, comment=None, encoding="utf-8-sig")
    except (ValueError, pd.errors.ParserError) as exc:
        raise _fail(path, f"cannot read the CSV table ({exc}); every row needs one number per header column "
                          "('nan' or empty for a missing sample)") from None
    variables = {name: frame[name].to_numpy(dtype=float) for name in header}
    return variables, units, attrs


def read_measurement(path: str | os.PathLike, concept: str | None = None) -> Measurement:
    """Read and validate a measurement file (``.nc`` or ``.csv``).

    Parameters
    ----------
    path : the file; its extension selects the format.
    concept : if given, the concept the caller expects; a file of another concept is an error.

    Returns
    -------
    Measurement whose experiment holds time [s] and inputs, ``values`` (n_samples, n_channels)
    in file column order, NaN where a sample is missing; ``attrs`` holds the file's provenance
    attributes (everything but ``concept`` and ``experiment``).

    Raises
    ------
    DataFileError (a ValueError) naming the file, the problem and the fix.
    """
    path = Path(path)
    if concept is not None:
        get_model(concept)  # an unknown requested concept is the caller's error, not the file's
    if path.suffix.lower() == ".mat":
        if concept is not None and concept != "emps":
            raise DataFileError(f"file {path} is a MATLAB file of the EMPS benchmark (concept emps), but {concept} "
                                "was asked for; give a .nc or .csv file of that concept or ask for emps")
        return read_emps(path)
    fmt = data_format(path)
    if not path.exists():
        raise _fail(path, "no such file; check the path (or create it with 'ema-uq simulate')")
    if path.is_dir():
        raise _fail(path, "this is a directory, not a data file; give the path of a .nc or .csv file")
    try:
        variables, units, attrs = _read_netcdf(path) if fmt == "netcdf" else _read_csv(path)
    except OSError as exc:
        raise _fail(path, f"cannot open the file ({exc.strerror or exc}); check its permissions") from None

    file_concept = attrs.pop("concept", None)
    if file_concept is None:
        where = "global attribute" if fmt == "netcdf" else "first-line comment"
        raise _fail(path, f"no concept given; add the {where} 'concept = htls' or 'concept = lths'")
    file_concept = str(file_concept).strip()
    try:
        model = get_model(file_concept)
    except ValueError as exc:
        raise _fail(path, str(exc)) from None
    if concept is not None and file_concept != concept:
        raise DataFileError(f"file {path} holds concept {file_concept}, but {concept} was asked for; "
                            "give a file of that concept or change the requested concept")

    valid = ("time",) + tuple(model.inputs) + tuple(model.outputs)
    unknown = [name for name in variables if name not in valid]
    if unknown:
        raise _fail(path, f"unknown channel name(s) {', '.join(unknown)} for concept {model.name}; "
                          f"valid names: {', '.join(valid)}")
    if "time" not in variables:
        raise _fail(path, "no 'time' column; add the sample times in seconds")
    time = variables["time"]
    if time.size == 0:
        raise _fail(path, "zero samples; a measurement needs at least two samples")
    for name, unit in units.items():
        if name not in variables:
            continue  # a unit for an absent column is harmless
        expected = TIME_UNIT if name == "time" else model.unit_of(name)
        if _normalize_unit(unit) != _normalize_unit(expected):
            raise _fail(path, f"variable {name} is in {unit!r}, but the package works in {expected!r}; "
                              f"convert {name} to {expected} (SI)")
    try:
        check_time_grid(time, where="time")
    except ExperimentError as exc:
        raise _fail(path, str(exc)) from None

    inputs = {name: variables[name] for name in model.inputs if name in variables}
    missing = [name for name in model.required_inputs if name not in inputs]
    if missing:
        raise _fail(path, f"missing required input(s) {', '.join(missing)}; "
                          f"a measurement file needs {', '.join(model.required_inputs)} beside time")
    for name, values in inputs.items():
        bad = ~np.isfinite(values)
        if bad.any():
            k = int(np.argmax(bad))
            raise _fail(path, f"input {name} has {int(bad.sum())} NaN or infinite sample(s), first at "
                              f"t = {time[k]:g} s; inputs must be complete (repair or trim the record)")
    channels = [name for name in variables if name in model.outputs]
    if not channels:
        raise _fail(path, f"no output channel; add at least one of {', '.join(model.outputs)}")
    values = np.column_stack([variables[name] for name in channels])
    if np.isinf(values).any():
        col = int(np.argmax(np.isinf(values).any(axis=0)))
        raise _fail(path, f"channel {channels[col]} holds infinite values; "
                          "mark missing samples with NaN (empty or 'nan' in CSV)")

    name = str(attrs.pop("experiment", path.stem))
    try:
        experiment = Experiment(name, time, inputs)
        return Measurement(model.name, experiment, tuple(channels), values, attrs)
    except (ExperimentError, ParameterError) as exc:
        raise _fail(path, str(exc)) from None


# --------------------------------------------------------------------------------------
# EMPS benchmark files (MATLAB, read-only)
# --------------------------------------------------------------------------------------
#: Environment variable that overrides the folder of the EMPS benchmark files.
EMPS_DIR_ENV = "EMA_UQ_EMPS_DIR"
#: Default folder of the EMPS files, relative to the repository root (the data live outside
#: the repository and are never copied into it).
DEFAULT_EMPS_DIR = "../shared/data/real/emps"
EMPS_FILES = {"estimation": "DATA_EMPS.mat", "validation": "DATA_EMPS_PULSES.mat"}
_EMPS_SIGNALS = ("t", "qm", "qg", "vir")
_EMPS_GAINS = ("kp", "kv", "gtau")
#: Channels :func:`read_emps` can return: measured ``qm``, ``vir`` and the two derived from
#: them, ``force`` = gtau·vir and ``qd_hat`` (the controller's velocity estimate from qm).
EMPS_CHANNELS = ("qm", "vir", "force", "qd_hat")
_TIME_JITTER = 1e-3  # tolerated deviation of a time stamp from the uniform grid, in samples


def repository_root() -> Path:
    """The folder holding the package directory (the repository root of an editable install)."""
    return Path(__file__).resolve().parent.parent


def emps_data_dir(study: Mapping[str, Any] | None = None) -> Path:
    """Folder of the EMPS benchmark files: ``$EMA_UQ_EMPS_DIR`` if set, else the study's
    ``data.path``, else :data:`DEFAULT_EMPS_DIR`; relative paths are taken from the
    repository root. The folder is not checked here (see :func:`emps_files`)."""
    env = os.environ.get(EMPS_DIR_ENV, "").strip()
    given = env or ((study or {}).get("data") or {}).get("path") or DEFAULT_EMPS_DIR
    folder = Path(os.path.expanduser(str(given)))
    return folder if folder.is_absolute() else (repository_root() / folder).resolve()


def emps_files(study: Mapping[str, Any] | None = None, *, must_exist: bool = True) -> dict[str, Path]:
    """``{"estimation": .../DATA_EMPS.mat, "validation": .../DATA_EMPS_PULSES.mat}``; the study's
    ``data.estimation`` / ``data.validation`` may name other files of the folder. With
    ``must_exist`` a missing file is a :class:`DataFileError` saying how to point at the data."""
    folder = emps_data_dir(study)
    data = (study or {}).get("data") or {}
    files = {}
    for role, default in EMPS_FILES.items():
        name = str(data.get(role, default))
        files[role] = folder / (name if name.lower().endswith(".mat") else default)
    if must_exist:
        for path in files.values():
            if not path.is_file():
                raise DataFileError(
                    f"file {path}: EMPS benchmark file not found; set {EMPS_DIR_ENV} or the study key data.path "
                    f"to the folder holding {', '.join(EMPS_FILES.values())}")
    return files


def _emps_vector(path: Path, raw: Mapping[str, Any], name: str, n: int | None) -> np.ndarray:
    value = np.asarray(raw[name])
    if value.dtype.kind not in "biuf":
        raise _fail(path, f"variable {name} holds {value.dtype} values; it must be numeric")
    value = value.astype(float).ravel()
    if value.ndim != 1 or value.size < 2 or (n is not None and value.size != n):
        raise _fail(path, f"variable {name} has shape {np.shape(raw[name])}; expected a vector of "
                          f"{n if n is not None else 'at least 2'} samples like t")
    return value


def read_emps(path: str | os.PathLike, channels: tuple[str, ...] = ("qm", "vir")) -> Measurement:
    """Read one EMPS benchmark file (``DATA_EMPS.mat`` or ``DATA_EMPS_PULSES.mat``) as an
    ``emps`` :class:`Measurement`.

    File variables (scipy.io.loadmat): ``t`` [s], ``qm`` [m] (encoder, load side), ``qg`` [m]
    (reference), ``vir`` [V] (logged drive command), scalars ``kp`` [1/s], ``kv`` [V/(m/s)],
    ``gtau`` [N/V], and in the validation file ``pulses_N`` (uint8, 0/5: volts of drive
    command despite the name, see SOURCE of the data).

    Returns a measurement of ``channels`` (any of :data:`EMPS_CHANNELS`, default qm and vir)
    with inputs ``qg`` and, when present, ``pulse`` [V]. The time stamps carry float jitter
    (~3e-8 s), so the grid is rebuilt uniform from the first and last stamp. ``attrs`` hold
    the file's gains, the initial state for the simulation (``q0`` = qm(0), ``qd0`` from a
    quadratic through the first three samples, ``u0`` = the first logged command without
    pulse) and the provenance; ``models.emps.constants_for`` turns them into constants.

    Raises :class:`DataFileError` naming the file, the problem and the fix.
    """
    from scipy.io import loadmat

    from .models.emps import controller_output

    path = Path(path)
    if path.suffix.lower() != ".mat":
        raise _fail(path, "not a .mat file; give DATA_EMPS.mat or DATA_EMPS_PULSES.mat of the EMPS benchmark")
    if not path.exists():
        raise _fail(path, f"no such file; check the path or set {EMPS_DIR_ENV} to the EMPS data folder")
    if path.is_dir():
        raise _fail(path, "this is a directory, not a data file; give the path of a .mat file")
    bad = [c for c in channels if c not in EMPS_CHANNELS]
    if bad or not channels:
        raise DataFileError(f"unknown EMPS channel(s) {', '.join(bad) or '(none given)'}; "
                            f"choose from {', '.join(EMPS_CHANNELS)}")
    try:
        raw = loadmat(path)
    except NotImplementedError:
        raise _fail(path, "MATLAB v7.3 (HDF5) files are not read; save the data with save(..., '-v7')") from None
    except OSError as exc:
        raise _fail(path, f"cannot open the file ({exc.strerror or exc}); check its permissions") from None
    except Exception as exc:  # scipy raises several types for a file that is not a MAT file
        raise _fail(path, f"not a readable MATLAB .mat file ({type(exc).__name__}: {exc}); "
                          "give an EMPS benchmark file") from None
    missing = [v for v in _EMPS_SIGNALS + _EMPS_GAINS if v not in raw]
    if missing:
        raise _fail(path, f"missing variable(s) {', '.join(missing)}; an EMPS file holds "
                          f"{', '.join(_EMPS_SIGNALS + _EMPS_GAINS)} (and pulses_N in the validation file)")
    t = _emps_vector(path, raw, "t", None)
    n = t.size
    signals = {name: _emps_vector(path, raw, name, n) for name in _EMPS_SIGNALS[1:]}
    gains = {}
    for name in _EMPS_GAINS:
        value = np.asarray(raw[name], dtype=float)
        if value.size != 1 or not np.isfinite(value).all() or not value.item() > 0:
            raise _fail(path, f"gain {name} must be one positive number, got {value.ravel()[:3]}")
        gains[name] = float(value.item())
    pulse = _emps_vector(path, raw, "pulses_N", n) if "pulses_N" in raw else None

    if not np.all(np.isfinite(t)):
        raise _fail(path, "time t contains NaN or infinite values; give finite times in seconds")
    dt = float((t[-1] - t[0]) / (n - 1))
    grid = t[0] + dt * np.arange(n)
    worst = int(np.argmax(np.abs(t - grid)))
    if not dt > 0 or abs(t[worst] - grid[worst]) > _TIME_JITTER * dt:
        raise _fail(path, f"time t is not a uniform grid (sample {worst} at {t[worst]:.9g} s, expected "
                          f"{grid[worst]:.9g} s); resample the record to a uniform grid")
    for name in ("qg",) + (("pulses_N",) if pulse is not None else ()):
        values = signals.get(name, pulse)
        if not np.all(np.isfinite(values)):
            k = int(np.argmax(~np.isfinite(values)))
            raise _fail(path, f"input {name} has NaN or infinite samples, first at t = {grid[k]:g} s; "
                              "inputs must be complete")
    for name in ("qm", "vir"):
        if np.isinf(signals[name]).any():
            raise _fail(path, f"signal {name} holds infinite values; mark missing samples with NaN")

    qm, vir = signals["qm"], signals["vir"]
    pulse_volts = np.zeros(n) if pulse is None else pulse
    derived = {"qm": qm, "vir": vir, "force": gains["gtau"] * vir,
               "qd_hat": controller_output(qm, signals["qg"], gains["kp"], gains["kv"], dt)[1]}
    values = np.column_stack([derived[c] for c in channels])
    inputs = {"qg": signals["qg"]}
    if pulse is not None:
        inputs["pulse"] = pulse_volts
    attrs = {
        "source": "measured: EMPS benchmark (Janot, Gautier, Brunot 2019)",
        "file": path.name,
        "kp": gains["kp"], "kv": gains["kv"], "gtau": gains["gtau"],
        "q0": float(qm[0]),
        "qd0": float((-3.0 * qm[0] + 4.0 * qm[1] - qm[2]) / (2.0 * dt)),
        "u0": float(vir[0] - pulse_volts[0]),
        "time_jitter_s": float(np.max(np.abs(t - grid))),
    }
    header = raw.get("__header__", b"")
    if isinstance(header, bytes):
        attrs["mat_header"] = header.decode("latin-1").strip()
    name = "emps-pulses" if pulse is not None else "emps-estimation"
    try:
        experiment = Experiment(name, grid, inputs)
        return Measurement("emps", experiment, tuple(channels), values, attrs)
    except (ExperimentError, ParameterError) as exc:
        raise _fail(path, str(exc)) from None


# --------------------------------------------------------------------------------------
# Cranfield linear-actuator records (CSV, read-only)
# --------------------------------------------------------------------------------------
#: Environment variable that overrides the folder of the Cranfield linear-actuator files.
CRANFIELD_DIR_ENV = "EMA_UQ_CRANFIELD_DIR"
#: Default folder of the Cranfield files, relative to the repository root.
DEFAULT_CRANFIELD_DIR = "../shared/data/real/cranfield_linear_actuator"
#: The record sets of the rig: the healthy one and the seeded faults (file stems).
CRANFIELD_FILES = ("normal", "backlash1", "backlash2", "lackLubrication1", "lackLubrication2")
_CRANFIELD_COLUMNS = ("set_point", "position_error", "current", "load", "run", "group", "time")
#: Channels :func:`read_cranfield` can return (``position`` = set point - position error).
CRANFIELD_CHANNELS = ("position", "position_error", "current")
CRANFIELD_SAMPLE_TIME = 0.04   # s (25 Hz)
CRANFIELD_BLOCK = 1620         # samples per (load, run): 5 motion cycles of 324 samples
_KGF = 9.80665                 # N per kgf


def cranfield_data_dir(study: Mapping[str, Any] | None = None) -> Path:
    """Folder of the Cranfield files: ``$EMA_UQ_CRANFIELD_DIR`` if set, else the study's
    ``data.path``, else :data:`DEFAULT_CRANFIELD_DIR`; relative paths are taken from the
    repository root. The folder is not checked here."""
    env = os.environ.get(CRANFIELD_DIR_ENV, "").strip()
    given = env or ((study or {}).get("data") or {}).get("path") or DEFAULT_CRANFIELD_DIR
    folder = Path(os.path.expanduser(str(given)))
    return folder if folder.is_absolute() else (repository_root() / folder).resolve()


def cranfield_file(name: str, study: Mapping[str, Any] | None = None, *, must_exist: bool = True) -> Path:
    """Path of the record set ``name`` (e.g. ``"normal"``, ``"backlash1"``; ``.csv`` optional);
    with ``must_exist`` a missing file is a :class:`DataFileError` saying how to point at the data."""
    stem = name[:-4] if name.lower().endswith(".csv") else name
    path = cranfield_data_dir(study) / f"{stem}.csv"
    if must_exist and not path.is_file():
        raise DataFileError(f"file {path}: Cranfield record set not found; set {CRANFIELD_DIR_ENV} or the study key "
                            f"data.path to the folder holding {', '.join(f + '.csv' for f in CRANFIELD_FILES)}")
    return path


def _cranfield_table(path: Path) -> dict[str, np.ndarray]:
    import pandas as pd

    if path.suffix.lower() != ".csv":
        raise _fail(path, "not a .csv file; give a record set of the Cranfield rig such as normal.csv")
    if not path.is_file():
        raise _fail(path, f"no such file; check the path or set {CRANFIELD_DIR_ENV} to the Cranfield data folder")
    try:
        frame = pd.read_csv(path, encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError, ValueError, pd.errors.ParserError) as exc:
        raise _fail(path, f"cannot read the CSV table ({_one_line(exc)}); give a comma-separated text file "
                          "with a header row") from None
    frame.columns = [str(c).strip() for c in frame.columns]
    missing = [c for c in _CRANFIELD_COLUMNS if c not in frame.columns]
    if missing:
        raise _fail(path, f"missing column(s) {', '.join(missing)}; a Cranfield record set has columns "
                          f"{', '.join(_CRANFIELD_COLUMNS)}")
    table = {}
    for name in _CRANFIELD_COLUMNS:
        values = pd.to_numeric(frame[name], errors="coerce").to_numpy(dtype=float)
        bad = ~np.isfinite(values)
        if bad.any():
            row = int(np.argmax(bad))
            raise _fail(path, f"column {name} has a missing or non-numeric value at data row {row + 1} "
                              f"({frame[name].iloc[row]!r}); repair or drop that row's block")
        table[name] = values
    return table


def _cranfield_block(path: Path, table: Mapping[str, np.ndarray], rows: np.ndarray, load: float,
                     run: int) -> np.ndarray:
    """The block's time axis [s] (0 ... 64.76) after checking its layout: 1620 consecutive rows,
    the cycle time within each ``group`` strictly increasing on the 0.04 s grid."""
    where = f"block load {load:g} kgf, run {run}"
    if rows.size != CRANFIELD_BLOCK or np.any(np.diff(rows) != 1):
        raise _fail(path, f"{where} has {rows.size} rows{'' if np.all(np.diff(rows) == 1) else ', not consecutive'}; "
                          f"each (load, run) block must be {CRANFIELD_BLOCK} consecutive rows (5 cycles at 25 Hz)")
    group, cycle_time = table["group"][rows], table["time"][rows]
    new_cycle = np.flatnonzero(np.diff(group) != 0) + 1
    for start, stop in zip(np.concatenate([[0], new_cycle]), np.concatenate([new_cycle, [rows.size]])):
        steps = np.diff(cycle_time[start:stop])
        if np.any(steps <= 0) or np.any(np.abs(steps - CRANFIELD_SAMPLE_TIME) > 1e-6):
            k = start + 1 + int(np.argmax((steps <= 0) | (np.abs(steps - CRANFIELD_SAMPLE_TIME) > 1e-6)))
            raise _fail(path, f"{where}: column time is not increasing by {CRANFIELD_SAMPLE_TIME} s at data row "
                              f"{rows[k] + 1} ({cycle_time[k - 1]:g} -> {cycle_time[k]:g} s); sort the rows of each "
                              "cycle by time")
        if cycle_time[start] != 0.0 and start > 0:
            raise _fail(path, f"{where}: cycle {int(group[start])} starts at time {cycle_time[start]:g} s, not 0; "
                              "a record set holds whole motion cycles")
    return np.round(np.arange(CRANFIELD_BLOCK) * CRANFIELD_SAMPLE_TIME, 10)


def read_cranfield(path: str | os.PathLike, *, loads: Sequence[float] | None = None,
                   runs: Sequence[int] | None = None,
                   channels: Sequence[str] = ("position", "current")) -> list[Measurement]:
    """Read one record set of the Cranfield linear actuator (``normal.csv``, ``backlash1.csv``,
    ...) as ``cranfield`` measurements, one per (load, run) block, loads in file order then runs.

    File columns: ``set_point`` [mm], ``position_error`` [mm] (set point - measured position),
    ``current`` [A], ``load`` [kgf] (20, 40, -40), ``run`` (1..10), ``group`` (motion cycle) and
    ``time`` [s] within the cycle. Each block is 1620 consecutive samples at 0.04 s; its time
    axis runs 0 ... 64.76 s. Inputs: ``x_sp`` [m] and ``F_load`` = load · g0 [N]; ``channels``
    any of :data:`CRANFIELD_CHANNELS` (``position`` [m] = set point - position error,
    ``position_error`` [m], ``current`` [A]). ``loads``/``runs`` select blocks (default all);
    asking for a block the file lacks is an error. ``attrs`` hold the file, record set, load
    [kgf], run and provenance.

    Raises :class:`DataFileError` naming the file, the problem and the fix.
    """
    path = Path(path)
    channels = tuple(channels)
    bad = [c for c in channels if c not in CRANFIELD_CHANNELS]
    if bad or not channels:
        raise DataFileError(f"unknown Cranfield channel(s) {', '.join(bad) or '(none given)'}; "
                            f"choose from {', '.join(CRANFIELD_CHANNELS)}")
    table = _cranfield_table(path)
    blocks = list(dict.fromkeys(zip(table["load"].tolist(), table["run"].astype(int).tolist())))
    wanted = [(ld, r) for ld, r in blocks
              if (loads is None or ld in [float(x) for x in loads]) and (runs is None or r in [int(x) for x in runs])]
    held_loads = list(dict.fromkeys(b[0] for b in blocks))
    held_runs = sorted({b[1] for b in blocks})
    absent = ([f"load {float(x):g} kgf" for x in (loads or ()) if float(x) not in held_loads]
              + [f"run {int(x)}" for x in (runs or ()) if int(x) not in held_runs])
    if absent:
        raise _fail(path, f"no block for {absent[0]}; the file holds loads {', '.join(f'{x:g}' for x in held_loads)} "
                          f"kgf and runs {', '.join(map(str, held_runs))}")
    if not wanted:
        raise _fail(path, "no (load, run) block matches the selection; choose loads and runs the file holds")
    measurements = []
    for ld, r in wanted:
        rows = np.flatnonzero((table["load"] == ld) & (table["run"] == r))
        time = _cranfield_block(path, table, rows, ld, r)
        set_point = table["set_point"][rows] * 1e-3
        error = table["position_error"][rows] * 1e-3
        derived = {"position": set_point - error, "position_error": error, "current": table["current"][rows]}
        inputs = {"x_sp": set_point, "F_load": np.full(rows.size, ld * _KGF)}
        attrs = {"source": "measured: Cranfield linear actuator (Ruiz-Carcel and Starr 2018), CSV conversion",
                 "file": path.name, "record_set": path.stem, "load_kgf": float(ld), "run": int(r)}
        try:
            experiment = Experiment(f"{path.stem} load {ld:g} kgf run {r}", time, inputs)
            measurements.append(Measurement("cranfield", experiment, channels,
                                            np.column_stack([derived[c] for c in channels]), attrs))
        except (ExperimentError, ParameterError) as exc:
            raise _fail(path, str(exc)) from None
    return measurements


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
