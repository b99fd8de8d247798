"""The EMPS benchmark files (MATLAB ``.mat``, read-only): where they are and how a record
becomes a :class:`~ema_uq.experiments.Measurement` with its gains and initial state."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..experiments import Experiment, ExperimentError, Measurement
from ..params import ParameterError
from .files import DataFileError, _fail, repository_root


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

    from ..models.emps import controller_output

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
