"""Study files: a file that is not YAML is refused naming the line and column."""
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
