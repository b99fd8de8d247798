"""Measurement files (NetCDF, CSV) and JSON result files: round trips and every way a
data file can be wrong, each reported as a one-line DataFileError naming the file."""
from __future__ import annotations

import json

import numpy as np
import pytest
import xarray as xr

from ema_uq import __version__, io
from ema_uq.experiments import Experiment, Measurement, deploy_retract
from ema_uq.io import DataFileError

FORMATS = ("nc", "csv")
N = 50  # samples: enough to exercise the layout, small enough to keep the tests instant


def _measurement(concept="htls", channels=("Omega", "y1", "I_A"), brake=False, seed=1) -> Measurement:
    experiment = deploy_retract().slice(100, 100 + N)  # a moving stretch: all inputs non-trivial
    if brake:
        inputs = dict(experiment.inputs, brake=np.linspace(0.0, 1.0, N))
        experiment = Experiment(experiment.name, experiment.time, inputs)
    values = np.random.default_rng(seed).normal(size=(N, len(channels))) * [10.0 ** -k for k in range(len(channels))]
    values[3, 0] = np.nan
    values[10:14, -1] = np.nan
    # strings that look like numbers or booleans, lists and newlines must survive both formats
    attrs = {"noise_fraction": 0.02, "seed": 7, "source": "simulated", "label": "0", "flag": "true",
             "gains": [1.5, 2.0], "tags": ["a", "b"], "note": "two\nlines"}
    return Measurement(concept, experiment, channels, values, attrs)


def _assert_same(read: Measurement, written: Measurement) -> None:
    assert read.concept == written.concept
    assert read.experiment.name == written.experiment.name
    assert read.channels == written.channels
    np.testing.assert_array_equal(read.time, written.time)
    assert set(read.experiment.inputs) == set(written.experiment.inputs)
    for name, values in written.experiment.inputs.items():
        np.testing.assert_array_equal(read.experiment.inputs[name], values)
    # assert_array_equal treats NaN == NaN, and a NaN read back as 0 would fail here
    np.testing.assert_array_equal(np.isnan(read.values), np.isnan(written.values))
    np.testing.assert_array_equal(read.values, written.values)
    assert read.attrs == {**written.attrs, "ema_uq_version": __version__}


# --------------------------------------------------------------------------------------
# round trips
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("ext", FORMATS)
def test_round_trip_htls(tmp_path, ext):
    m = _measurement()
    path = io.write_measurement(tmp_path / f"m.{ext}", m)
    _assert_same(io.read_measurement(path), m)
    _assert_same(io.read_measurement(path, concept="htls"), m)


@pytest.mark.parametrize("ext", FORMATS)
def test_round_trip_lths_with_brake_and_all_outputs(tmp_path, ext):
    from ema_uq import get_model

    outputs = get_model("lths").outputs
    m = _measurement("lths", channels=outputs, brake=True)
    path = io.write_measurement(tmp_path / "sub" / "dir" / f"m.{ext}", m)  # parents created
    _assert_same(io.read_measurement(path, concept="lths"), m)


def test_round_trip_of_simulated_data(tmp_path):
    from ema_uq import synthesize

    m = synthesize("htls", deploy_retract().slice(0, 120), noise=0.02, seed=5)
    for ext in FORMATS:
        _assert_same(io.read_measurement(io.write_measurement(tmp_path / f"s.{ext}", m)), m)


def test_netcdf_layout_units_and_concept(tmp_path):
    path = io.write_measurement(tmp_path / "m.nc", _measurement())
    ds = xr.load_dataset(path, engine="h5netcdf", decode_times=False, decode_timedelta=False)
    assert ds.attrs["concept"] == "htls"
    assert ds.attrs["experiment"] == "deploy-retract"
    assert ds.attrs["seed"] == 7 and ds.attrs["source"] == "simulated"
    assert ds["time"].attrs["units"] == "s"
    units = {name: ds[name].attrs["units"] for name in ds.data_vars}
    assert units == {"phi_r": "rad", "F_ER1": "N", "F_ER2": "N", "Omega": "rad/s", "y1": "m", "I_A": "A"}
    assert ds["Omega"].dims == ("time",) and ds.sizes["time"] == N
    assert np.isnan(ds["Omega"].values[3])


def test_csv_layout_units_and_concept(tmp_path):
    path = io.write_measurement(tmp_path / "m.csv", _measurement())
    lines = path.read_text().splitlines()
    assert lines[0] == "# concept = htls"
    assert lines[1] == "# units: time=s,phi_r=rad,F_ER1=N,F_ER2=N,Omega=rad/s,y1=m,I_A=A"
    assert "# experiment = deploy-retract" in lines
    assert "# source = simulated" in lines
    assert '# label = "0"' in lines  # a string that looks like a number stays a string
    header = next(line for line in lines if not line.startswith("#"))
    assert header == "time,phi_r,F_ER1,F_ER2,Omega,y1,I_A"
    assert ",nan," in lines[lines.index(header) + 4]  # sample 3 of Omega is missing


def test_csv_hand_written_file_with_empty_fields(tmp_path):
    """A minimal hand-written CSV: bare concept, no units, empty field as a missing sample."""
    path = tmp_path / "hand.csv"
    path.write_text("\ufeff# concept = lths\n"  # with the byte-order mark of spreadsheet exports
                    'time, phi_r, F_ER1, F_ER2, "Omega"\n'
                    "0.0, 0, -1000, -800, 1.5\n"
                    "0.5, 0.1, -1000, -800,\n"
                    "1.0, 0.2, -1000, -800, NaN\n", encoding="utf-8")
    m = io.read_measurement(path)
    assert m.concept == "lths" and m.channels == ("Omega",)
    assert m.experiment.name == "hand" and m.experiment.dt == pytest.approx(0.5)
    assert m.values[0, 0] == 1.5 and np.isnan(m.values[1:, 0]).all()
    assert m.attrs == {}


def test_attrs_bool_is_stored_as_integer(tmp_path):
    m = _measurement()
    m = Measurement(m.concept, m.experiment, m.channels, m.values, {"clean": True})
    for ext in FORMATS:
        assert io.read_measurement(io.write_measurement(tmp_path / f"b.{ext}", m)).attrs["clean"] == 1


@pytest.mark.parametrize("attrs, problem", [
    ({"concept": "lths"}, "reserved"),
    ({"bad key": 1}, "not valid"),
    ({"nested": {"a": 1}}, "type dict"),
    ({"mixed": [1, "a"]}, "cannot be stored"),
])
def test_write_rejects_unstorable_attrs(tmp_path, attrs, problem):
    m = _measurement()
    m = Measurement(m.concept, m.experiment, m.channels, m.values, attrs)
    with pytest.raises(DataFileError, match=problem):
        io.write_measurement(tmp_path / "m.nc", m)
    assert not (tmp_path / "m.nc").exists()


def test_write_unknown_extension_and_unwritable_location(tmp_path):
    with pytest.raises(DataFileError, match="unknown file extension '.txt'"):
        io.write_measurement(tmp_path / "m.txt", _measurement())
    blocker = tmp_path / "plain-file"
    blocker.write_text("x")
    with pytest.raises(DataFileError, match="is a file, not a directory"):
        io.write_measurement(blocker / "m.nc", _measurement())


def test_failed_write_leaves_no_file(tmp_path, monkeypatch):
    def broken(self, *args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(xr.Dataset, "to_netcdf", broken)
    with pytest.raises(DataFileError, match="disk full"):
        io.write_measurement(tmp_path / "m.nc", _measurement())
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------------------
# bad files: raw writers that bypass the validating writer
# --------------------------------------------------------------------------------------
def _raw_content() -> dict:
    time = np.round(np.arange(N) * 0.01, 10)
    return {
        "attrs": {"concept": "htls"},
        "units": {"time": "s", "phi_r": "rad", "F_ER1": "N", "F_ER2": "N", "Omega": "rad/s", "y1": "m"},
        "vars": {"time": time, "phi_r": np.linspace(0, 0.1, N), "F_ER1": np.full(N, -3e3),
                 "F_ER2": np.full(N, -2e3), "Omega": np.sin(time), "y1": np.cos(time)},
    }


def _write_raw(path, content) -> None:
    if path.suffix == ".nc":
        data_vars = {}
        for name, values in content["vars"].items():
            if name == "time":
                continue
            dims = ("time",) if np.ndim(values) == 1 else ("time", "extra")
            data_vars[name] = (dims, values, {"units": content["units"].get(name, "1")})
        coords = {}
        if "time" in content["vars"]:
            coords["time"] = ("time", content["vars"]["time"], {"units": content["units"].get("time", "s")})
        xr.Dataset(data_vars, coords=coords, attrs=content["attrs"]).to_netcdf(path, engine="h5netcdf")
    else:
        names = list(content["vars"])
        lines = [f"# {k} = {v}" for k, v in content["attrs"].items()]
        lines.append("# units: " + ",".join(f"{n}={content['units'][n]}" for n in names if n in content["units"]))
        lines.append(",".join(names))
        columns = np.column_stack([content["vars"][n] for n in names]) if names else np.empty((0, 0))
        lines += [",".join(f"{v!r}" for v in row) for row in columns.tolist()]
        path.write_text("\n".join(lines) + "\n")


def _expect_error(path, *fragments, concept=None) -> str:
    with pytest.raises(DataFileError) as info:
        io.read_measurement(path, concept=concept)
    message = str(info.value)
    assert "\n" not in message, message
    assert str(path) in message, message
    for fragment in fragments:
        assert fragment in message, message
    return message


def _mutated(tmp_path, ext, mutate):
    content = _raw_content()
    mutate(content)
    path = tmp_path / f"bad.{ext}"
    _write_raw(path, content)
    return path


def test_raw_writer_baseline_is_valid(tmp_path):
    """The bad-file cases below differ from this valid file in one thing each."""
    for ext in FORMATS:
        m = io.read_measurement(_mutated(tmp_path, ext, lambda c: None))
        assert m.channels == ("Omega", "y1") and m.experiment.n_samples == N


def _set_time(values):
    def mutate(c):
        c["vars"]["time"] = values
    return mutate


def _nonuniform():
    t = np.round(np.arange(N) * 0.01, 10)
    t[20:] += 0.005
    return t


def _decreasing():
    t = np.round(np.arange(N) * 0.01, 10)
    t[30] = t[28]
    return t


def _nan_time():
    t = np.round(np.arange(N) * 0.01, 10)
    t[5] = np.nan
    return t


def _drop(*names):
    def mutate(c):
        for n in names:
            del c["vars"][n]
    return mutate


def _add(name, values, unit="1"):
    def mutate(c):
        c["vars"][name] = values
        c["units"][name] = unit
    return mutate


def _nan_at(name, k):
    def mutate(c):
        c["vars"][name] = c["vars"][name].copy()
        c["vars"][name][k] = np.nan
    return mutate


def _inf_output(c):
    c["vars"]["Omega"] = c["vars"]["Omega"].copy()
    c["vars"]["Omega"][7] = np.inf


def _attrs(attrs):
    def mutate(c):
        c["attrs"] = attrs
    return mutate


def _unit(name, unit):
    def mutate(c):
        c["units"][name] = unit
    return mutate


def _zero_samples(c):
    c["vars"] = {k: v[:0] for k, v in c["vars"].items()}


def _one_sample(c):
    c["vars"] = {k: v[:1] for k, v in c["vars"].items()}


BAD_CASES = [
    ("missing_concept", _attrs({}), ("no concept", "concept = htls")),
    ("unknown_concept", _attrs({"concept": "foo"}), ("unknown concept 'foo'", "htls, lths")),
    ("non_uniform_time", _set_time(_nonuniform()), ("time is not uniform", "resample")),
    ("non_increasing_time", _set_time(_decreasing()), ("time is not strictly increasing at sample 30",)),
    ("nan_time", _set_time(_nan_time()), ("time contains NaN",)),
    ("missing_time", _drop("time"), ("no 'time'",)),
    ("missing_inputs", _drop("F_ER2", "phi_r"), ("missing required input(s) phi_r, F_ER2",)),
    ("unknown_channels", _add("Omegaa", np.zeros(N)),
     ("unknown channel name(s) Omegaa", "valid names: time, phi_r, F_ER1, F_ER2, brake, Omega, y1")),
    ("channel_of_other_concept", _add("U_A", np.zeros(N), "V"), ("unknown channel name(s) U_A", "concept htls")),
    ("input_nan", _nan_at("phi_r", 4), ("input phi_r has 1 NaN", "t = 0.04 s", "inputs must be complete")),
    ("no_output_channel", _drop("Omega", "y1"), ("no output channel", "add at least one of Omega")),
    ("infinite_output", _inf_output, ("channel Omega holds infinite values", "NaN")),
    ("zero_samples", _zero_samples, ("zero samples",)),
    ("one_sample", _one_sample, ("at least two samples",)),
    ("wrong_unit", _unit("phi_r", "deg"), ("phi_r is in 'deg'", "convert phi_r to rad")),
    ("wrong_time_unit", _unit("time", "ms"), ("time is in 'ms'",)),
]


@pytest.mark.parametrize("ext", FORMATS)
@pytest.mark.parametrize("mutate, fragments", [c[1:] for c in BAD_CASES], ids=[c[0] for c in BAD_CASES])
def test_bad_content(tmp_path, ext, mutate, fragments):
    _expect_error(_mutated(tmp_path, ext, mutate), *fragments)


@pytest.mark.parametrize("ext", FORMATS)
def test_concept_mismatch(tmp_path, ext):
    path = _mutated(tmp_path, ext, _attrs({"concept": "lths"}))
    _expect_error(path, f"file {path} holds concept lths, but htls was asked for", concept="htls")


def test_unknown_requested_concept_is_the_callers_error(tmp_path):
    path = _mutated(tmp_path, "nc", lambda c: None)
    with pytest.raises(ValueError, match="unknown concept 'emx'"):
        io.read_measurement(path, concept="emx")


def test_two_dimensional_variable(tmp_path):
    path = _mutated(tmp_path, "nc", _add("Omega", np.zeros((N, 3)), "rad/s"))
    _expect_error(path, "variable Omega has dimensions ('time', 'extra')", "(50, 3)", "1-D along 'time'")


def test_variable_on_another_dimension(tmp_path):
    path = tmp_path / "bad.nc"
    content = _raw_content()
    ds = xr.Dataset({n: ("time", v) for n, v in content["vars"].items() if n != "time"},
                    coords={"time": content["vars"]["time"]}, attrs={"concept": "htls"})
    ds["y2"] = ("sample", np.zeros(7))
    ds.to_netcdf(path, engine="h5netcdf")
    _expect_error(path, "variable y2 has dimensions ('sample',)")


def test_non_numeric_netcdf_variable(tmp_path):
    content = _raw_content()
    content["vars"]["y1"] = np.array(["a"] * N, dtype=object)
    path = tmp_path / "bad.nc"
    _write_raw(path, content)
    _expect_error(path, "variable y1 holds", "store numbers")


@pytest.mark.parametrize("ext", FORMATS)
def test_missing_file(tmp_path, ext):
    _expect_error(tmp_path / f"absent.{ext}", "no such file", "check the path")


@pytest.mark.parametrize("ext", FORMATS)
def test_empty_file(tmp_path, ext):
    path = tmp_path / f"empty.{ext}"
    path.write_bytes(b"")
    _expect_error(path, "the file is empty")


def test_directory_instead_of_file(tmp_path):
    path = tmp_path / "dir.nc"
    path.mkdir()
    _expect_error(path, "this is a directory")


def test_unknown_extension(tmp_path):
    path = tmp_path / "data.txt"
    path.write_text("time,phi_r\n")
    _expect_error(path, "unknown file extension '.txt'", ".nc", ".csv")


def test_text_file_named_nc(tmp_path):
    path = tmp_path / "fake.nc"
    path.write_text("# concept = htls\ntime,phi_r\n0,0\n")
    _expect_error(path, "not a NetCDF file")


def test_truncated_netcdf(tmp_path):
    good = io.write_measurement(tmp_path / "good.nc", _measurement())
    path = tmp_path / "truncated.nc"
    path.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    _expect_error(path, "cannot read the NetCDF file", "not corrupted")


def test_binary_file_named_csv(tmp_path):
    path = tmp_path / "binary.csv"
    path.write_bytes(b"\x89HDF\r\n\x1a\n\xff\xfe\x00\x01" * 10)
    _expect_error(path, "not a text CSV file")


@pytest.mark.parametrize("row, fragment", [
    ("0.02,0,-3000,-2000,1,2,99", "cannot read the CSV table"),  # one field too many
    ("0.02,0,-3000,-2000,abc,2", "cannot read the CSV table"),    # not a number
    ("0.02,0,-3000,-2000", "line 5 has 4 of the header's 6 fields"),  # cut off: not missing samples
    ("0.02,0,-3000,-2000,,", None),                                # empty fields: missing samples
])
def test_malformed_csv_rows(tmp_path, row, fragment):
    path = tmp_path / "bad.csv"
    path.write_text("# concept = htls\ntime,phi_r,F_ER1,F_ER2,Omega,y1\n"
                    "0,0,-3000,-2000,1,2\n0.01,0,-3000,-2000,1,2\n" + row + "\n")
    if fragment is None:
        assert np.isnan(io.read_measurement(path).values[-1]).all()
    else:
        _expect_error(path, fragment)


def test_csv_duplicate_and_missing_header(tmp_path):
    path = tmp_path / "dup.csv"
    path.write_text("# concept = htls\ntime,phi_r,F_ER1,F_ER2,Omega,Omega\n0,0,0,0,1,1\n0.01,0,0,0,1,1\n")
    _expect_error(path, "column(s) Omega appear more than once")
    path = tmp_path / "noheader.csv"
    path.write_text("# concept = htls\n")
    _expect_error(path, "no header row")


def test_netcdf3_classic_file_is_read(tmp_path):
    content = _raw_content()
    ds = xr.Dataset({n: ("time", v) for n, v in content["vars"].items() if n != "time"},
                    coords={"time": content["vars"]["time"]}, attrs={"concept": "htls"})
    path = tmp_path / "classic.nc"
    ds.to_netcdf(path, engine="scipy")
    assert io.read_measurement(path).channels == ("Omega", "y1")


# --------------------------------------------------------------------------------------
# JSON result files
# --------------------------------------------------------------------------------------
def test_json_round_trip_with_numpy_values(tmp_path):
    obj = {"concept": "htls", "cost": np.float64(1.5e-3), "iterations": np.int64(7),
           "converged": np.bool_(True), "estimate": np.array([1.0, 2.0]),
           "correlation": np.eye(2), "labels": ("a", "b"), "bad": float("nan"), "none": None}
    path = io.write_json(tmp_path / "deep" / "fit.json", obj)
    text = path.read_text()
    assert text.startswith("{\n  ")  # indent 2
    assert "NaN" not in text  # strict JSON for non-Python readers
    back = io.read_json(path)
    assert back == {"concept": "htls", "cost": 1.5e-3, "iterations": 7, "converged": True,
                    "estimate": [1.0, 2.0], "correlation": [[1.0, 0.0], [0.0, 1.0]],
                    "labels": ["a", "b"], "bad": None, "none": None}
    assert json.loads(text) == back


def test_json_errors(tmp_path):
    with pytest.raises(DataFileError, match="no such file"):
        io.read_json(tmp_path / "absent.json")
    bad = tmp_path / "bad.json"
    bad.write_text('{"a": 1,,}')
    with pytest.raises(DataFileError, match=r"not valid JSON .* line 1"):
        io.read_json(bad)
    with pytest.raises(DataFileError, match="cannot store a object"):
        io.write_json(tmp_path / "x.json", {"x": object()})
    assert not (tmp_path / "x.json").exists()
