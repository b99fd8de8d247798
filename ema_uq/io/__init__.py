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

The parts: :mod:`.files` (the error, formats and output checks every part shares),
:mod:`.measurement` (NetCDF and CSV), :mod:`.emps` and :mod:`.cranfield` (the two measured
rigs' files) and :mod:`.results` (JSON).
"""
from .cranfield import (CRANFIELD_BLOCK, CRANFIELD_CHANNELS, CRANFIELD_DIR_ENV, CRANFIELD_FILES, CRANFIELD_HEALTHY,
                        CRANFIELD_SAMPLE_TIME, DEFAULT_CRANFIELD_DIR, CranfieldRecords, cranfield_data_dir,
                        cranfield_file, cranfield_record_sets, read_cranfield)
from .emps import DEFAULT_EMPS_DIR, EMPS_CHANNELS, EMPS_DIR_ENV, EMPS_FILES, emps_data_dir, emps_files, read_emps
from .files import FORMATS, TIME_UNIT, DataFileError, data_format, prepare_output, repository_root
from .measurement import read_measurement, write_measurement
from .results import _jsonable, read_benchmark, read_json, write_json  # noqa: F401 - _jsonable: for tests of result files

__all__ = [
    "DataFileError", "FORMATS", "data_format", "prepare_output", "write_measurement", "read_measurement",
    "write_json", "read_json", "read_benchmark", "read_emps", "emps_data_dir", "emps_files", "EMPS_DIR_ENV",
    "read_cranfield", "cranfield_data_dir", "cranfield_file", "cranfield_record_sets", "CranfieldRecords",
    "CRANFIELD_DIR_ENV", "CRANFIELD_HEALTHY",
    "TIME_UNIT", "repository_root", "DEFAULT_EMPS_DIR", "EMPS_CHANNELS", "EMPS_FILES", "DEFAULT_CRANFIELD_DIR",
    "CRANFIELD_FILES", "CRANFIELD_CHANNELS", "CRANFIELD_SAMPLE_TIME", "CRANFIELD_BLOCK",
]
