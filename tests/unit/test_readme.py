"""The README's library example is code a newcomer pastes first: it must run as written."""
import re
from pathlib import Path

README = Path(__file__).resolve().parents[2] / "README.md"


def test_the_library_example_runs_as_written(capsys):
    section = README.read_text(encoding="utf-8").split("### Library", 1)[1]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    exec(compile(code, "README.md (Library)", "exec"), {"__name__": "readme_example"})
    printed = capsys.readouterr().out
    assert "[[Fit: htls by ML GN]]" in printed and "converged          = True" in printed
    assert "(2, 3800, 16)" in printed
