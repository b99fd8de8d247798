"""Study files: a file that is not YAML is refused naming the line and column; a value the model
cannot take is refused before any stage runs."""
import re

import pytest

from ema_uq import cli
from ema_uq.study import StudyError, load_study


@pytest.mark.parametrize("text,where", [
    ("name: x\n  concept: htls\n", "line 2, column 10"),           # a key indented under a value
    ("name: x\ndata:\n  noise: [0.02\n", "line 4, column 1"),        # a bracket never closed
])
def test_malformed_yaml_names_line_and_column(tmp_path, capsys, text, where):
    path = tmp_path / "study.yaml"
    path.write_text(text)
    with pytest.raises(StudyError, match=f"not valid YAML at {where}: "):
        load_study(path)
    assert cli.main(["check-study", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and where in err


def test_the_study_schema_accepts_exactly_the_gap_method_versions():
    """``gap.method_version``: the schema's choices are the package's versions (a version added
    to the package and not to the schema could not be chosen in a study)."""
    import json
    from pathlib import Path

    import ema_uq
    from ema_uq.gap.strategy import METHOD_VERSIONS

    schema = json.loads((Path(ema_uq.__file__).parent / "schema" / "study.schema.json").read_text())
    choices = schema["properties"]["gap"]["properties"]["method_version"]["enum"]
    assert sorted(v for v in choices if v is not None) == sorted(METHOD_VERSIONS)


@pytest.mark.parametrize("entry,message", [
    ("J: -5", "J = -5 lies outside its bounds [1e-06, inf]"),       # an estimated parameter
    ("k_n: 0", "k_n = 0 lies outside its bounds"),
    ("J: .nan", "J = nan lies outside its bounds"),                  # not a number
])
def test_a_data_set_value_outside_its_bounds_is_refused_before_any_stage(tmp_path, capsys, entry, message):
    path = tmp_path / "study.yaml"
    path.write_text(f"name: x\nconcept: htls\ndata:\n  set: {{{entry}}}\n")
    with pytest.raises(StudyError, match=re.escape(f"key 'data.set': {message}")):
        load_study(path)
    assert cli.main(["check-study", str(path)]) == 2
    assert capsys.readouterr().err.count("\n") == 1
    path.write_text("name: x\nconcept: htls\ndata:\n  set: {J: 0.05}\n")
    assert load_study(path)["data"]["set"] == {"J": 0.05}
