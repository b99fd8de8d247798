"""The gap method version as a choice of the user: `--method-version N` on `ema-uq gap` and
`ema-uq gap-selfcheck`, the study key `gap.method_version`, one table of versions in the package."""
from __future__ import annotations

import dataclasses

import pytest
import yaml

from ema_uq import cli, io
from ema_uq.gap.strategy import (DEFAULT_METHOD_VERSION, METHOD_VERSIONS, DiagnosisSettings, method_switches,
                                 method_version_of)
from ema_uq.study import StudyError, load_study, settings_for


def test_the_default_settings_are_the_default_version_and_every_version_differs():
    assert DiagnosisSettings() == DiagnosisSettings(**method_switches(DEFAULT_METHOD_VERSION))
    switches = [method_switches(v) for v in METHOD_VERSIONS]
    assert all(a != b for i, a in enumerate(switches) for b in switches[i + 1:])
    assert method_switches(7)["decision_stop"] == "predicted" and not method_switches(1)["model_form_allowance"]
    # version 10 is the default's forms and fits at the converged step, nothing else
    assert {k for k, v in method_switches(10).items() if method_switches(4)[k] != v} == {"converged_step"}
    with pytest.raises(ValueError, match="no gap method version 11; choose from 1, 2, 3, 4, 5, 6, 7, 8, 9, 10"):
        method_switches(11)


def _study(tmp_path, concept: str, **gap) -> str:
    path = tmp_path / f"{concept}.yaml"
    path.write_text(yaml.safe_dump({"name": "s", "concept": concept, "gap": gap}))
    return str(path)


def test_a_study_names_the_version_for_both_gap_verbs_and_not_for_a_measured_rig(tmp_path):
    study = load_study(_study(tmp_path, "htls", method_version=7))
    assert settings_for(study, "gap")["method_version"] == 7 == settings_for(study, "gap-selfcheck")["method_version"]
    assert settings_for(load_study(_study(tmp_path, "lths")), "gap")["method_version"] is None
    with pytest.raises(StudyError, match="method_version"):
        load_study(_study(tmp_path, "htls", method_version=11))
    with pytest.raises(StudyError, match="'gap.method_version'.*measured rig"):
        load_study(_study(tmp_path, "cranfield", method_version=7))


class _Diagnosed:
    """What the gap verb reads of a diagnosis result, without diagnosing."""
    concept, wall_time_s, provenance = "htls", 0.0, None
    gap = {"before": 0.1, "after": 0.1, "shrink": None}

    def to_json(self):
        return {"verdict": "none"}

    def headline(self):
        return "none"


def test_the_gap_verb_diagnoses_with_the_version_asked_for_and_says_which(short_htls_record, tmp_path, monkeypatch, capsys):
    import ema_uq.gap as gap

    seen = []

    def fake_diagnose(*args, settings=None, **kwargs):
        seen.append(settings)
        return _Diagnosed()

    monkeypatch.setattr(gap, "diagnose", fake_diagnose)
    written = []
    record = short_htls_record
    other = 7 if DEFAULT_METHOD_VERSION != 7 else 4
    for extra in ([], ["--method-version", str(other)], ["--study", _study(tmp_path, "htls", method_version=2)]):
        assert cli.main(["gap", str(record), "--concept", "htls", "--out", str(tmp_path / "g.json"), *extra]) == 0
        written.append(io.read_json(tmp_path / "g.json")["method_version"])
    assert written == [DEFAULT_METHOD_VERSION, other, 2]
    assert [s.decision_stop for s in seen] == [method_switches(v)["decision_stop"]
                                               for v in (DEFAULT_METHOD_VERSION, other, 2)]
    assert seen[0] == dataclasses.replace(seen[0], **method_switches(DEFAULT_METHOD_VERSION))
    assert seen[1] == dataclasses.replace(seen[0], **method_switches(other))    # the rest of the strategy's settings kept
    assert seen[2] == dataclasses.replace(seen[0], **method_switches(2))
    capsys.readouterr()
    assert cli.main(["gap", str(record), "--concept", "htls", "--method-version", "11", "--out",
                     str(tmp_path / "g11.json")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--method-version 11: no gap method version 11" in err
    assert not (tmp_path / "g11.json").exists()


def test_settings_name_their_version_or_none():
    for version in METHOD_VERSIONS:
        assert method_version_of(DiagnosisSettings(**method_switches(version))) == version
    assert method_version_of(DiagnosisSettings(spanning_forms=False, decision_fits=True)) is None


def test_the_selfcheck_verb_passes_the_version_to_every_case(tmp_path, monkeypatch):
    from ema_uq.gap import selfcheck

    seen = {}

    def fake_self_check(**kwargs):
        seen.update(kwargs)
        raise selfcheck.SelfCheckError("stopped here by the test")

    monkeypatch.setattr(selfcheck, "self_check", fake_self_check)
    assert cli.main(["gap-selfcheck", "--quick", "--method-version", "7", "--out", str(tmp_path / "s.json")]) == 2
    assert seen["settings"] == DiagnosisSettings(**method_switches(7))
    assert cli.main(["gap-selfcheck", "--quick", "--out", str(tmp_path / "s.json")]) == 2
    assert seen["settings"] is None


def test_a_measured_rig_refuses_a_method_version():
    from ema_uq.cli.arguments import CLIError
    from ema_uq.cli.diagnosis import _method_switches

    assert _method_switches(None, "emps") == {}
    with pytest.raises(CLIError, match="emps is a measured rig"):
        _method_switches(7, "emps")


def test_the_measured_rigs_keep_their_switches_when_the_synthetic_default_changes():
    """A new default is decided on simulated records; it must not reach EMPS or Cranfield unseen.
    The rigs are imported in a fresh interpreter whose default settings are another version's."""
    import subprocess
    import sys

    from ema_uq import rigs

    assert rigs.MEASURED_RIG_METHOD_VERSION == 4
    other = next(v for v in METHOD_VERSIONS if v != rigs.MEASURED_RIG_METHOD_VERSION)
    script = (
        "import functools\n"
        "from ema_uq.gap import strategy\n"
        "strategy.DiagnosisSettings = functools.partial(strategy.DiagnosisSettings,"
        f" **strategy.method_switches({other}))\n"
        "from ema_uq.rigs import cranfield, emps\n"
        "print(strategy.method_version_of(emps.EMPS_STRATEGY.settings),"
        " strategy.method_version_of(cranfield.cranfield_strategy().settings))\n")
    shown = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True).stdout
    assert shown.split() == ["4", "4"]
