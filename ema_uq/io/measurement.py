"""Measurement files of every concept: NetCDF (``.nc``) and CSV (``.csv``), written and read
against the layout of :mod:`ema_uq.io`; a MATLAB file of the EMPS benchmark is handed to
:func:`ema_uq.io.emps.read_emps`."""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from ..experiments import Experiment, ExperimentError, Measurement, check_time_grid
from ..models import get_model
from ..params import ParameterError
from .files import (TIME_UNIT, _HDF5_MAGIC, _NETCDF3_MAGIC, _VERSION_KEY, DataFileError, _atomic_write, _check_attrs,
                    _fail, _normalize_unit, _python_value, data_format)
from .emps import read_emps


# --------------------------------------------------------------------------------------
# writing
# --------------------------------------------------------------------------------------
def _layout(path: Path, measurement: Measurement):
    """(names, units, columns, global attrs) shared by both writers, time first."""
    from .. import __version__

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
    # pandas pads a short row with NaN, which would read a cut-off line as missing samples
    for number, line in enumerate(body_lines[1:], start=n_comments + 2):
        if line.strip() and line.count(",") < len(header) - 1:
            raise _fail(path, f"line {number} has {line.count(',') + 1} of the header's {len(header)} fields; "
                              "every row needs one number per header column ('nan' or empty for a missing sample)")
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
    empty = [c for c, name in enumerate(channels) if not np.isfinite(values[:, c]).any()]
    if empty:
        raise _fail(path, f"channel {channels[empty[0]]} has no sample (every value missing); drop the column or "
                          "give its values")

    name = str(attrs.pop("experiment", path.stem))
    try:
        experiment = Experiment(name, time, inputs)
        return Measurement(model.name, experiment, tuple(channels), values, attrs)
    except (ExperimentError, ParameterError) as exc:
        raise _fail(path, str(exc)) from None
