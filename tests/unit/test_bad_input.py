"""Bad input found by an audit of every verb: each gets one clear line and exit status 2, and no
output file, where before it passed silently (a wrong answer), hung or ended in a traceback."""
from __future__ import annotations

import numpy as np
import pytest

from ema_uq import cli
from ema_uq.experiments import MAX_MAGNITUDE, Experiment, ExperimentError


@pytest.fixture(scope="module")
def record(short_htls_record):
    """A short HT/LS record (the first 2 s of deploy-retract, every channel)."""
    return short_htls_record


def _error(capsys, args) -> str:
    try:
        code = cli.main(args)
    except SystemExit as stop:          # the option parser's own errors end the process
        code = stop.code
    err = capsys.readouterr().err
    assert code == cli.EXIT_ERROR and err.startswith("ema-uq: error:") and err.count("\n") == 1, err
    return err


def _corrupt(path, tmp_path, column: str, row: int, value: str):
    lines = path.read_text().splitlines()
    header = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    names = lines[header].split(",")
    cells = lines[header + 1 + row].split(",")
    cells[names.index(column)] = value
    lines[header + 1 + row] = ",".join(cells)
    out = tmp_path / f"{column}_{row}.csv"
    out.write_text("\n".join(lines) + "\n")
    return out


@pytest.mark.parametrize("column, kind", [("phi_r", "input"), ("Omega", "channel")])
def test_a_corrupt_huge_sample_is_refused_not_fitted(record, tmp_path, capsys, column, kind):
    """One sample of 1e300 used to pass: identify then returned another inertia, gap a high-confidence verdict."""
    bad = _corrupt(record, tmp_path, column, 50, "1e300")
    out = tmp_path / "fit.json"
    err = _error(capsys, ["identify", str(bad), "--concept", "htls", "--max-iterations", "2", "--out", str(out)])
    assert f"{kind} {column}" in err and "1e+300" in err and "corrupt" in err and not out.exists()


def test_magnitude_bound_is_far_above_any_rig_quantity_and_checks_inputs_and_channels():
    time = np.arange(5) * 0.01
    Experiment("ok", time, {"phi_r": np.full(5, 1e3), "F_ER1": np.full(5, 1e5), "F_ER2": np.zeros(5)})
    with pytest.raises(ExperimentError, match="input F_ER1 has a sample of 2e\\+12 at t = 0.02 s"):
        Experiment("x", time, {"phi_r": np.zeros(5), "F_ER1": np.array([0, 0, 2 * MAX_MAGNITUDE, 0, 0]),
                               "F_ER2": np.zeros(5)})


def _rewrite_column(path, out, column: str, rewrite) -> None:
    """A copy of CSV record ``path`` at ``out`` with every value of ``column`` passed through ``rewrite``."""
    lines = path.read_text().splitlines()
    header = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    c = lines[header].split(",").index(column)
    for i in range(header + 1, len(lines)):
        cells = lines[i].split(",")
        cells[c] = rewrite(cells[c])
        lines[i] = ",".join(cells)
    out.write_text("\n".join(lines) + "\n")


def test_a_time_column_in_milliseconds_is_refused_not_simulated_for_hours(record, tmp_path, capsys):
    bad = tmp_path / "ms.csv"
    _rewrite_column(record, bad, "time", lambda cell: repr(float(cell) * 1000.0))
    err = _error(capsys, ["identify", str(bad), "--concept", "htls", "--out", str(tmp_path / "fit.json")])
    assert "steps by 10 s" in err and "seconds" in err


def test_a_channel_without_any_sample_is_refused(record, tmp_path, capsys):
    bad = tmp_path / "empty_channel.csv"
    _rewrite_column(record, bad, "Omega", lambda cell: "nan")
    err = _error(capsys, ["gap", str(bad), "--concept", "htls", "--candidates", "backlash",
                          "--out", str(tmp_path / "gap.json")])
    assert "channel Omega has no sample" in err


@pytest.mark.parametrize("args, fragment", [
    (["identify", "{record}", "--concept", "htls", "--max-iterations", "-3", "--out", "{out}"], "positive integer"),
    (["sample", "{record}", "--concept", "htls", "--init", "x.json", "--predictive", "-1", "--out", "{out}"],
     "non-negative integer"),
    (["simulate", "--concept", "htls", "--experiment", "deploy-retract", "--noise", "1e300", "--out", "{out}"],
     "over 0.5"),
    (["gap", "{record}", "--concept", "htls", "--figure", "{tmp}/ledger.txt", "--out", "{out}"],
     "cannot write a figure as .txt"),
])
def test_impossible_options_are_refused_before_any_work(record, tmp_path, capsys, args, fragment):
    out = tmp_path / "out.json"
    args = [a.format(record=record, out=out, tmp=tmp_path) for a in args]
    assert fragment in _error(capsys, args) and not out.exists()


def test_a_key_given_twice_in_a_study_is_an_error_not_the_last_one_silently(tmp_path, capsys):
    study = tmp_path / "twice.yaml"
    study.write_text("name: twice\nconcept: htls\nseed: 1\ndata:\n  noise: 0.02\nseed: 5\n")
    err = _error(capsys, ["check-study", str(study)])
    assert "key 'seed' is given twice (line 6)" in err


def test_report_refuses_an_empty_results_folder_and_a_directory_as_output(tmp_path, capsys):
    (tmp_path / "results").mkdir()
    err = _error(capsys, ["report", "--study", "studies/smoke.yaml", "--results", str(tmp_path / "results"),
                          "--out", str(tmp_path / "r.html")])
    assert "no stage result" in err and not (tmp_path / "r.html").exists()
    (tmp_path / "results" / "fit.json").write_text("{}")
    err = _error(capsys, ["report", "--study", "studies/smoke.yaml", "--results", str(tmp_path / "results"),
                          "--out", str(tmp_path)])
    assert "this is a directory; give a file name" in err
