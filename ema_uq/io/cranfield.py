"""The Cranfield linear-actuator record sets (CSV, read-only): where they are and how each
(load, run) block becomes a :class:`~ema_uq.experiments.Measurement`."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from ..experiments import Experiment, ExperimentError, Measurement
from ..params import ParameterError
from .files import DataFileError, _fail, _one_line, repository_root


# --------------------------------------------------------------------------------------
# Cranfield linear-actuator records (CSV, read-only)
# --------------------------------------------------------------------------------------
#: Environment variable that overrides the folder of the Cranfield linear-actuator files.
CRANFIELD_DIR_ENV = "EMA_UQ_CRANFIELD_DIR"
#: Default folder of the Cranfield files, relative to the repository root.
DEFAULT_CRANFIELD_DIR = "../shared/data/real/cranfield_linear_actuator"
#: The record sets of the rig: the healthy one and the seeded faults (file stems).
CRANFIELD_FILES = ("normal", "backlash1", "backlash2", "lackLubrication1", "lackLubrication2")
#: The healthy record set, the one the rig model is fitted on (file stem).
CRANFIELD_HEALTHY = "normal"
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


def cranfield_record_sets(study: Mapping[str, Any] | None = None) -> list[str]:
    """The record sets a fault diagnosis of the rig reads (file stems, the healthy one first):
    the study's ``data.record_sets`` when given (each must exist), else every ``.csv`` file of the
    data folder (so a record set added to the folder is diagnosed without naming it anywhere),
    the rig's known sets in :data:`CRANFIELD_FILES` order, then the others in natural order
    (``spalling2`` before ``spalling10``). Without a data folder: :data:`CRANFIELD_FILES`
    (nothing is read; the caller reports the missing files). The healthy set must be there."""
    import re

    folder = cranfield_data_dir(study)
    given = ((study or {}).get("data") or {}).get("record_sets")
    if given:
        names = [n[:-4] if str(n).lower().endswith(".csv") else str(n) for n in given]
        for name in names:
            cranfield_file(name, study)
        names = [CRANFIELD_HEALTHY] + [n for n in dict.fromkeys(names) if n != CRANFIELD_HEALTHY]
    elif not folder.is_dir():
        return list(CRANFIELD_FILES)
    else:
        found = sorted(p.stem for p in folder.glob("*.csv") if p.is_file())
        natural = sorted((n for n in found if n not in CRANFIELD_FILES),
                         key=lambda n: [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", n)])
        names = [n for n in CRANFIELD_FILES if n in found] + natural
    if CRANFIELD_HEALTHY not in names:
        raise DataFileError(f"folder {folder}: no {CRANFIELD_HEALTHY}.csv; the fault diagnosis fits the rig on its "
                            f"healthy records first: put {CRANFIELD_HEALTHY}.csv beside the record sets")
    return names


class CranfieldRecords:
    """The record sets of one data folder (the study's), each file read once: ``read(name, runs)``
    returns the blocks of those runs (None: all) as :func:`read_cranfield` would, for a study
    and its run splits that ask for the same files again and again; ``runs_of(name)`` the runs a
    set holds."""

    def __init__(self, study: Mapping[str, Any] | None = None, channels: Sequence[str] = ("position", "current")):
        self.study, self.channels = study, tuple(channels)
        self._blocks: dict[str, list[Measurement]] = {}

    def read(self, name: str, runs: Sequence[int] | None = None) -> list[Measurement]:
        if name not in self._blocks:
            self._blocks[name] = read_cranfield(cranfield_file(name, self.study), channels=self.channels)
        blocks = self._blocks[name]
        if runs is None:
            return list(blocks)
        wanted = {int(r) for r in runs}
        if not wanted <= {m.attrs["run"] for m in blocks}:  # the reader's own error names the run that lacks
            return read_cranfield(cranfield_file(name, self.study), runs=runs, channels=self.channels)
        return [m for m in blocks if m.attrs["run"] in wanted]

    def runs_of(self, name: str) -> list[int]:
        return sorted({m.attrs["run"] for m in self.read(name)})


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
