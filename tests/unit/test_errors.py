"""One error root: every user error derives from EmaUqError; the command line tells a user
error (one line, exit 2) from a fault of the package (traceback, exit 3)."""
from __future__ import annotations

import importlib
import inspect
import pkgutil
import re
from pathlib import Path

import pytest

import ema_uq
from ema_uq import cli
from ema_uq.cli import reporting
from ema_uq.errors import EmaUqError


def _error_classes():
    """Every class named ``...Error`` that a module of the package defines."""
    root = Path(ema_uq.__file__).parent
    found = {}
    for info in pkgutil.walk_packages([str(root)], prefix="ema_uq."):
        source = Path(importlib.util.find_spec(info.name).origin)
        if not re.search(r"^class \w+Error\(", source.read_text(encoding="utf-8"), re.M):
            continue
        module = importlib.import_module(info.name)
        for name, obj in vars(module).items():
            if (inspect.isclass(obj) and issubclass(obj, BaseException) and name.endswith("Error")
                    and obj.__module__ == info.name):
                found[f"{info.name}.{name}"] = obj
    return found


def test_every_error_class_derives_from_the_root():
    classes = _error_classes()
    assert len(classes) >= 18
    strays = [name for name, cls in classes.items() if not issubclass(cls, EmaUqError)]
    assert not strays
    assert issubclass(EmaUqError, ValueError)  # callers that caught ValueError keep working


def test_user_error_is_one_line_exit_2(monkeypatch, capsys):
    def bad_input(args):
        raise EmaUqError("the study names no concept;\n  give one")

    monkeypatch.setattr(reporting, "_run_check_study", bad_input)
    assert cli.main(["check-study", "x.yaml"]) == cli.EXIT_ERROR
    err = capsys.readouterr().err
    assert err == "ema-uq: error: the study names no concept; give one\n"


def test_missing_file_is_a_user_error(tmp_path, capsys):
    assert cli.main(["check-study", str(tmp_path / "missing.yaml")]) == cli.EXIT_ERROR
    err = capsys.readouterr().err
    assert err.startswith("ema-uq: error:") and err.count("\n") == 1


@pytest.mark.parametrize("bug", [ValueError("math domain error"), KeyError("omega"), ZeroDivisionError()])
def test_a_fault_of_the_package_shows_its_traceback(monkeypatch, capsys, bug):
    def broken(args):
        raise bug

    monkeypatch.setattr(reporting, "_run_check_study", broken)
    assert cli.main(["check-study", "x.yaml"]) == cli.EXIT_BUG
    err = capsys.readouterr().err
    assert "Traceback (most recent call last)" in err and type(bug).__name__ in err
    assert "please report it" in err
    assert "ema-uq: error:" not in err
