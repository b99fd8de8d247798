"""The self-check harness: left-out families, stressed no-effect cases, target status,
scatter/gather and the frozen protocol of benchmarks/gap.py."""
from __future__ import annotations

import contextlib
import dataclasses
import importlib.util
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from ema_uq.cli import main as cli_main
from ema_uq.gap import selfcheck
from ema_uq.gap.candidates import OPERATING_POINT_FORMS, SPANNING_FORMS
from ema_uq.gap.variants import VARIANTS
from ema_uq.models import get_model

ROOT = Path(__file__).resolve().parents[2]


# --------------------------------------------------------------------------------------
# left-out families
# --------------------------------------------------------------------------------------
def test_left_out_cases_lack_every_form_of_their_family_and_carry_it():
    cases = selfcheck.build_cases(["htls", "lths"], seed=11, kinds=["left_out"])
    inside = [v for v, var in VARIANTS.items() if var.family is not None]
    assert len(cases) == 2 * 2 * len(inside) and {c.kind for c in cases} == {"left_out"}
    families = {c.family for c in cases}
    assert families == {var.family for var in VARIANTS.values() if var.family is not None}   # every family
    for case in cases:
        catalogue = {n: e for n, e in get_model(case.concept).effect_catalogue.items()   # method version 2's
                     if not e.combines and n not in SPANNING_FORMS + OPERATING_POINT_FORMS}
        forms = [n for n, e in catalogue.items() if (getattr(e, "family", None) or n) == case.family]
        assert forms and not set(forms) & set(case.candidates)                 # the family's forms are gone
        assert set(case.candidates) | set(forms) == set(catalogue)             # and nothing else
        assert VARIANTS[case.variant].family == case.family and case.expected == "unexplained"
    # other records than the in-catalogue case of the same variant; the records carry the variant
    effect = {c.case_id: c for c in selfcheck.build_cases(["htls"], seed=11, sensors=["realistic"], kinds=["effect"])}
    case = next(c for c in cases if c.concept == "htls" and c.sensors == "realistic"
                and c.variant == "backlash_output_deadzone")
    assert case.seed != effect["htls/realistic/backlash_output_deadzone"].seed
    *_, truth = selfcheck.case_records(case)
    assert truth["variant"] == "backlash_output_deadzone" and truth["family"] == "backlash"
    assert truth["parameters"]["delta"] > 0


def test_a_left_out_case_hands_the_reduced_catalogue_to_the_diagnosis(monkeypatch):
    seen = {}

    def fake(measurements, validation, *, candidates=None, settings=None, seed=None):
        seen["candidates"] = candidates
        raise RuntimeError("stop")

    monkeypatch.setattr(selfcheck, "diagnose", fake)
    monkeypatch.setattr(selfcheck, "case_records",
                        lambda case: (None, None, None, {"parameters": {}, "stress": {}}))
    case = selfcheck._case(11, "htls", "full", "stribeck_rational", left_out=True)
    outcome = selfcheck.run_case(case)
    assert outcome.verdict == "error" and "stribeck" not in seen["candidates"]
    assert set(seen["candidates"]) == set(case.candidates)


def test_a_case_whose_records_fail_is_that_cases_error_not_the_campaigns(monkeypatch):
    def broken(case):
        raise FloatingPointError("variant diverged")

    monkeypatch.setattr(selfcheck, "case_records", broken)
    case = selfcheck._case(11, "htls", "full", "stribeck_rational")
    outcome = selfcheck.run_case(case)
    assert outcome.verdict == "error" and outcome.message == "FloatingPointError: variant diverged"
    assert outcome.parameters == {} and not outcome.correct


def _outcome(kind, family, verdict, found=None, confidence="high", stressed=False, index=-1):
    variant = {"effect": f"{family}_v", "left_out": f"{family}_v", "none": None, "out_of_catalogue": "gremlin"}[kind]
    case = selfcheck.Case(f"htls/full/{variant}/{index}", "htls", "full", kind, variant,
                          family if kind in ("effect", "left_out") else None, 7, stressed)
    return selfcheck.CaseOutcome(case, verdict, found and f"{found}_form", found if verdict == "effect" else None,
                                 confidence, float("nan"), float("nan"), None, 0.02, 0.02, {}, 1.0, index=index)


def test_left_out_scores_confusion_and_confident_wrong_family():
    result = selfcheck.SelfCheckResult([
        _outcome("left_out", "backlash", "unexplained"),
        _outcome("left_out", "backlash", "ambiguous"),
        _outcome("left_out", "backlash", "effect", "shaft_compliance", "high"),     # confident and wrong
        _outcome("left_out", "stribeck", "effect", "load_dependent_friction", "low"),
        _outcome("left_out", "stribeck", "none"),
        _outcome("effect", "stribeck", "effect", "stribeck", "high"),
        _outcome("effect", "sensor_delay", "effect", "backlash", "high"),           # confident and wrong
        _outcome("out_of_catalogue", None, "effect", "stribeck", "low"),
        _outcome("none", None, "none"),
        _outcome("none", None, "unexplained", confidence="low", stressed=True),     # soft alarm: right
        _outcome("none", None, "unexplained", confidence="high", stressed=True),    # neither false nor right
        _outcome("none", None, "ambiguous", stressed=True),                         # names effects: false alarm
    ], seed=11, quick=False, wall_time_s=1.0)
    assert result.left_out_flagged["count"] == 2 and result.left_out_flagged["n"] == 5
    assert result.wrong_family_confident["count"] == 2 and result.wrong_family_confident["n"] == 8
    assert result.false_alarms["count"] == 1 and result.soft_alarms["count"] == 1 and result.any_alarm["count"] == 3
    assert result.hard_alarms["count"] == 1
    by_stress = result.false_alarms_by_stress
    assert by_stress["stressed"]["false"]["count"] == 1 and by_stress["plain"]["false"]["n"] == 1
    assert [o.correct for o in result.of("none")] == [True, True, False, False]
    lofo = result.confusion_left_out()
    assert lofo == {"backlash": {"unexplained": 1, "ambiguous": 1, "shaft_compliance": 1},
                    "stribeck": {"load_dependent_friction": 1, "none": 1}}
    assert "backlash" not in result.confusion().get("outside catalogue", {})
    text = result.summary()
    assert "left-out families" in text and "wrong family, high confidence" in text
    data = json.loads(json.dumps(result.to_json()))
    assert data["confusion_left_out"] == lofo and set(data["status"]) == set(selfcheck.TARGETS)
    assert selfcheck.SelfCheckResult.from_json(data).to_json() == result.to_json()


# --------------------------------------------------------------------------------------
# target status
# --------------------------------------------------------------------------------------
def test_target_status_says_n_too_small_unless_the_one_sided_bound_shows_it():
    status = selfcheck.target_status
    assert status(1, 1, 0.90, ">=") == "n too small"              # never met on one case
    assert status(0, 1, 0.90, ">=") == "n too small"
    assert status(0, 0, 0.90, ">=") == "n too small"
    assert status(29, 29, 0.90, ">=") == "met"                    # 0.95^(1/29) > 0.90 > 0.95^(1/28)
    assert status(28, 28, 0.90, ">=") == "n too small"
    assert status(5, 20, 0.90, ">=") == "not met"
    assert status(0, 59, 0.05, "<=") == "met" and status(0, 58, 0.05, "<=") == "n too small"
    assert status(0, 59, 0.05, "<=", minimum_n=60) == "n too small"
    assert status(6, 20, 0.05, "<=") == "not met"
    result = selfcheck.SelfCheckResult([_outcome("effect", "stribeck", "effect", "stribeck")], 1, False, 1.0)
    assert result.status["top1_accuracy"] == "n too small" and result.met["top1_accuracy"] is False
    assert result.status["left_out_flagged"] == "n too small"     # no cases at all


# --------------------------------------------------------------------------------------
# stressed no-effect cases
# --------------------------------------------------------------------------------------
def test_every_second_none_case_is_stressed_and_its_stress_is_seeded():
    nones = selfcheck.build_cases(["htls"], seed=11, sensors=["realistic"], kinds=["none"], none_per_set=6)
    assert [c.stressed for c in nones] == [False, True] * 3
    assert all(("stressed" in c.case_id) is c.stressed for c in nones)
    assert selfcheck.case_stress(nones[0]) is None
    a, b = selfcheck.case_stress(nones[1]), selfcheck.case_stress(nones[1])
    assert a == b and a != selfcheck.case_stress(nones[3])
    *_, truth = selfcheck.case_records(nones[1])
    assert truth["stress"]["ar1"] == a["ar1"] and truth["stress"]["constants"] == a["constants"]


# --------------------------------------------------------------------------------------
# scatter and gather
# --------------------------------------------------------------------------------------
def _fake_run_case(case, settings=None):
    verdict = {"effect": "effect", "none": "none", "out_of_catalogue": "unexplained", "left_out": "ambiguous"}[case.kind]
    family = case.family if case.kind == "effect" and case.seed % 3 else None
    if case.kind == "effect" and family is None:
        verdict = "unexplained"
    return selfcheck.CaseOutcome(case, verdict, family and f"{family}_form", family, "high", float(case.seed % 7) / 7,
                                 0.01, None, 0.02, 0.01, {"x": float(case.seed % 5)}, 0.5)


def test_a_case_whose_diagnosis_raised_ends_the_run_as_a_fault(monkeypatch, tmp_path, capsys):
    """A crash is not a wrong verdict: the outcomes are written, and the verb exits with the
    package-fault status naming the case, so a workflow stops instead of reporting the scores."""
    def crashing(case, settings=None):
        if case.kind == "none":
            return selfcheck.CaseOutcome(case, "error", None, None, "-", float("nan"), float("nan"), None,
                                         float("nan"), float("nan"), {}, 0.1, message="RuntimeError: boom")
        return _fake_run_case(case)

    monkeypatch.setattr(selfcheck, "run_case", crashing)
    out = tmp_path / "part.json"
    args = ["gap-selfcheck", "--seed", "11", "--concepts", "htls", "--sensors", "realistic", "--none-per-set", "2",
            "--kinds", "none,out_of_catalogue", "--quiet", "--out", str(out)]
    assert cli_main(args) == 3
    err = capsys.readouterr().err
    kept = selfcheck.SelfCheckResult.from_json(json.loads(out.read_text()))     # every outcome written
    verdicts = [o.verdict for o in kept.outcomes]
    assert verdicts.count("error") == 2 and "unexplained" in verdicts
    assert f"2 of {len(verdicts)} self-check cases ended in an error" in err and "RuntimeError: boom" in err
    # gathering parts that hold such cases is refused the same way
    assert cli_main(["gap-selfcheck", "--gather", str(out), "--out", str(tmp_path / "all.json")]) == 3
    monkeypatch.setattr(selfcheck, "run_case", _fake_run_case)
    assert cli_main(args) == 0


def test_chunks_gathered_equal_one_run(monkeypatch, tmp_path):
    monkeypatch.setattr(selfcheck, "run_case", _fake_run_case)
    kw = dict(seed=11, concepts=["htls"], sensors=["realistic"], none_per_set=3)

    def comparable(result):
        data = result.to_json()
        data.pop("wall_time_s"), data.pop("provenance")
        return data

    whole = selfcheck.self_check(**kw)
    parts = [selfcheck.self_check(**kw, chunk=f"{i}/3") for i in (2, 0, 1)]
    assert sum(len(p.outcomes) for p in parts) == len(whole.outcomes) and len(parts[1].outcomes) >= 1
    assert comparable(selfcheck.gather(parts)) == comparable(whole)
    # through JSON files and the CLI verb
    files = []
    for i in range(3):
        out = tmp_path / f"part_{i}.json"
        assert cli_main(["gap-selfcheck", "--seed", "11", "--concepts", "htls", "--sensors", "realistic",
                         "--none-per-set", "3", "--chunk", f"{i}/3", "--quiet", "--out", str(out)]) == 0
        files.append(str(out))
    assert cli_main(["gap-selfcheck", "--gather", *files, "--out", str(tmp_path / "all.json")]) == 0
    gathered = selfcheck.SelfCheckResult.from_json(json.loads((tmp_path / "all.json").read_text()))
    assert comparable(gathered) == comparable(whole)
    with pytest.raises(selfcheck.SelfCheckError, match="chunks 0/3..2/3"):
        selfcheck.gather(parts[:2])
    other = selfcheck.self_check(**{**kw, "seed": 12}, chunk="0/3")
    with pytest.raises(selfcheck.SelfCheckError, match="different runs"):
        selfcheck.gather([other, parts[0], parts[2]])
    with pytest.raises(selfcheck.SelfCheckError, match="0..N-1"):
        selfcheck.parse_chunk("3/3")


def test_cache_resumes_without_diagnosing_again(monkeypatch, tmp_path):
    calls = []

    def counting(case, settings=None):
        calls.append(case.case_id)
        return _fake_run_case(case)

    monkeypatch.setattr(selfcheck, "run_case", counting)
    kw = dict(seed=11, concepts=["htls"], sensors=["full"], none_per_set=2, kinds=["none", "out_of_catalogue"],
              cache=tmp_path / "cases")
    first = selfcheck.self_check(**kw, chunk="0/2")
    n_first = len(calls)
    whole = selfcheck.self_check(**kw)
    assert len(calls) == n_first + (len(whole.outcomes) - len(first.outcomes))   # only the others ran
    assert [o.to_json() for o in whole.outcomes[::2]] == [o.to_json() for o in first.outcomes]


def test_cache_diagnoses_again_a_case_that_raised(monkeypatch, tmp_path):
    """A case whose diagnosis raised is kept in the cache (for inspection) but not read back: a
    resumed run, after the cause is mended, diagnoses it again instead of scoring the old crash."""
    calls = []
    broken = {"on": True}

    def flaky(case, settings=None):
        calls.append(case.case_id)
        outcome = _fake_run_case(case)
        if broken["on"] and len(calls) == 1:
            outcome = dataclasses.replace(outcome, verdict="error", message="RuntimeError: a crash")
        return outcome

    monkeypatch.setattr(selfcheck, "run_case", flaky)
    kw = dict(seed=11, concepts=["htls"], sensors=["full"], none_per_set=2, kinds=["none"], cache=tmp_path / "c")
    first = selfcheck.self_check(**kw)
    assert [o.verdict for o in first.outcomes].count("error") == 1 and len(calls) == 2
    assert len(list((tmp_path / "c").glob("*.json"))) == 2   # the crash's outcome is on disk
    broken["on"] = False
    again = selfcheck.self_check(**kw)
    assert len(calls) == 3                                   # only the case that raised ran again
    assert "error" not in [o.verdict for o in again.outcomes]


def test_cache_does_not_read_back_outcomes_of_other_settings(monkeypatch, tmp_path):
    """A cache filled under other settings (an earlier default method) is diagnosed again, not
    counted for the settings of this run; a file written before settings were recorded is read."""
    from ema_uq.gap.strategy import DiagnosisSettings

    calls = []

    def counting(case, settings=None):
        calls.append(settings)
        return _fake_run_case(case)

    monkeypatch.setattr(selfcheck, "run_case", counting)
    kw = dict(seed=11, concepts=["htls"], sensors=["full"], none_per_set=2, kinds=["none"], cache=tmp_path / "c")
    version2 = DiagnosisSettings(spanning_forms=False)
    selfcheck.self_check(**kw, settings=version2)
    assert len(calls) == 2
    selfcheck.self_check(**kw, settings=version2)
    assert len(calls) == 2                                   # same settings: read back
    selfcheck.self_check(**kw)                               # the defaults (version 4): diagnosed again
    assert len(calls) == 4 and calls[-1] is None
    for path in (tmp_path / "c").glob("*.json"):             # as written before settings were recorded
        data = json.loads(path.read_text())
        del data["diagnosis_settings"]
        path.write_text(json.dumps(data))
    selfcheck.self_check(**kw, settings=version2)
    assert len(calls) == 4


# --------------------------------------------------------------------------------------
# the frozen protocol (benchmarks/gap.py)
# --------------------------------------------------------------------------------------
def _bench():
    spec = importlib.util.spec_from_file_location("gap_bench", ROOT / "benchmarks" / "gap.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _copy_of_the_sources(bench, root: Path) -> Path:
    """The diagnosis sources the protocol hashes, copied under ``root`` (to be changed there)."""
    for rel in bench.SOURCE_FILES + bench.source_globs(ROOT):
        target = root / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(ROOT / rel, target)
    return root


def test_the_protocol_hashes_every_module_a_diagnosis_computes_with():
    bench = _bench()
    code = ("import sys, ema_uq.gap.attribute, ema_uq.gap.selfcheck, ema_uq.gap.variants\n"
            "print('\\n'.join(m.__file__ for n, m in sys.modules.items() if n.startswith('ema_uq')))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                          cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    imported = {Path(f).resolve().relative_to(ROOT).as_posix() for f in done.stdout.split()}
    hashed = set(bench.source_globs(ROOT)) | set(bench.SOURCE_FILES)
    assert "ema_uq/identify/estimators.py" in imported and "ema_uq/simulate/integrators.py" in imported
    assert imported - hashed - bench.UNHASHED_MODULES == set()
    assert set(bench.hash_sources(ROOT)[1]) == hashed


def test_protocol_refuses_the_evaluation_block_when_a_source_changed(tmp_path, monkeypatch):
    bench = _bench()
    root = _copy_of_the_sources(bench, tmp_path / "repo")
    protocol = tmp_path / "protocol.yaml"
    frozen = bench.freeze(protocol, root=root, development=[11], evaluation=[5201])
    assert frozen["blocks"]["evaluation"]["seeds"] == [5201] and len(frozen["sources"]["sha256"]) == 64
    # the model-form allowance the strategy fits is part of the frozen method, with its bounds
    allowance = frozen["strategies"]["htls"]["model_form"]
    assert frozen["settings"]["model_form_allowance"] is True
    assert "r" in allowance["kinematic_constants"] and 0.0 < allowance["command_lag_max_s"] < 1.0
    assert bench.check_sources(bench.load_protocol(protocol), root=root) is None
    with open(root / "ema_uq" / "gap" / "attribute.py", "a", encoding="utf-8") as fh:
        fh.write("\n# changed\n")
    message = bench.check_sources(bench.load_protocol(protocol), root=root)
    assert message is not None and "--freeze" in message and "\n" not in message
    assert "ema_uq/gap/attribute.py" in message
    monkeypatch.setattr(bench, "run_block", lambda *a, **k: pytest.fail("ran a block"))
    with pytest.raises(SystemExit, match="--freeze"):
        bench.protocol_main(protocol, "evaluation", root=root, out_dir=tmp_path / "out")
    # re-freezing writes a new hash and a new evaluation block, the old one recorded as spent
    again = bench.freeze(protocol, root=root)
    assert again["sources"]["sha256"] != frozen["sources"]["sha256"]
    assert again["blocks"]["evaluation"]["spent"] == [[5201]]
    new = again["blocks"]["evaluation"]["seeds"]
    assert not set(new) & {5201, 11} and again["blocks"]["development"]["seeds"] == [11]
    assert bench.check_sources(bench.load_protocol(protocol), root=root) is None


def test_a_method_version_is_frozen_with_its_own_settings_and_catalogue(tmp_path):
    """A version under evaluation is frozen in a file of its own (the default version's protocol
    untouched); a protocol that predates a setting runs without it."""
    from ema_uq.gap.strategy import DiagnosisSettings

    bench = _bench()
    root = _copy_of_the_sources(bench, tmp_path / "repo")
    frozen = bench.freeze(tmp_path / "v4.yaml", root=root, development=[11], evaluation=[5205], method_version=4)
    assert frozen["method_version"] == 4 and frozen["settings"]["spanning_forms"] is True
    assert all(frozen["strategies"][c]["settings"]["spanning_forms"] is True for c in ("htls", "lths"))
    assert frozen["catalogue"]["lths"]["load_dependent_friction"] == ["load_dependent_friction",
                                                                      "load_friction_directional"]
    assert bench.protocol_settings(frozen).spanning_forms is True
    version2 = bench.freeze(tmp_path / "v2.yaml", root=root, development=[11], evaluation=[5206], method_version=2)
    assert version2["catalogue"]["lths"]["stribeck"] == ["stribeck"]
    older = {k: v for k, v in version2["settings"].items() if k != "spanning_forms"}
    assert bench.protocol_settings({"settings": older}).spanning_forms is False
    assert bench.method_settings(4) == bench.protocol_settings(frozen)
    # the code's defaults are the default method version's settings
    assert bench.method_settings(bench.DEFAULT_METHOD_VERSION) == DiagnosisSettings()
    default = bench.freeze(tmp_path / "default.yaml", root=root, development=[11], evaluation=[5207])
    assert "method_version" not in default and bench.protocol_settings(default) == DiagnosisSettings()
    assert bench.method_settings(7).decision_stop == "predicted"
    assert bench.method_settings(6).decision_stop == "extrapolated"
    assert bench.method_settings(8).nested_starts and not bench.method_settings(4).nested_starts
    assert bench.protocol_settings(frozen).nested_starts is False    # a protocol frozen before the switch
    assert bench.method_settings(9).nested_start_tolerance == 10.0 and bench.method_settings(9).nested_starts
    assert bench.protocol_settings(frozen).nested_start_tolerance == 0.0
    assert bench.method_settings(10).converged_step and not bench.method_settings(4).converged_step
    with pytest.raises(SystemExit, match="no gap method version 11"):
        bench.method_settings(11)


def test_the_committed_protocol_fixes_catalogue_thresholds_and_blocks():
    bench = _bench()
    protocol = bench.load_protocol(ROOT / "benchmarks" / "gap_protocol.yaml")
    for concept in ("htls", "lths"):
        assert protocol["catalogue"][concept] == selfcheck.catalogue_families(concept)
    assert protocol["thresholds"]["bic_min"] > 0 and "max_effects" in protocol["settings"]
    dev, ev = protocol["blocks"]["development"]["seeds"], protocol["blocks"]["evaluation"]["seeds"]
    assert dev and ev and not set(dev) & set(ev) and not set(ev) & {1, 2, 2024, *selfcheck.CALIBRATION_SEEDS}
    assert set(protocol["sources"]["files"]) >= {"ema_uq/gap/attribute.py", "ema_uq/models/effects.py",
                                                 "ema_uq/models/effect_kernels.py", "ema_uq/models/htls.py",
                                                 "ema_uq/models/lths.py", "ema_uq/models/cranfield.py"}
    assert protocol["selfcheck"]["none_per_set"] * 4 >= 60


def test_a_protocol_frozen_before_a_switch_existed_keeps_running_without_it(monkeypatch):
    import dataclasses

    from ema_uq.gap.strategy import DiagnosisSettings

    bench = _bench()
    version4 = dataclasses.asdict(bench.method_settings(4))
    before_version5 = {k: v for k, v in version4.items()
                       if k not in ("operating_point_forms", "nested_forms", "decision_fits", "decision_stop")}

    @dataclasses.dataclass(frozen=True)
    class LaterDefaults(DiagnosisSettings):  # the defaults of a later default method
        operating_point_forms: bool = True
        nested_forms: bool = False
        decision_fits: bool = True
        decision_stop: str = "predicted"

    monkeypatch.setattr(bench, "DiagnosisSettings", LaterDefaults)
    assert dataclasses.asdict(bench.protocol_settings({"settings": before_version5})) == version4


def test_the_version7_protocol_records_the_stop_it_runs_with():
    protocol = _bench().load_protocol(ROOT / "benchmarks" / "gap_protocol_v7.yaml")
    assert protocol["method_version"] == 7 and protocol["settings"]["decision_stop"] == "predicted"
    assert all(protocol["strategies"][c]["settings"]["decision_stop"] == "predicted" for c in ("htls", "lths"))
    assert protocol["blocks"]["evaluation"]["seeds"] == [5208]


def test_a_protocol_runs_the_method_version_it_was_frozen_for():
    bench = _bench()
    version1 = bench.protocol_settings({"settings": {"max_effects": 1}})
    version2 = bench.protocol_settings({"settings": {"max_effects": 1, "model_form_allowance": True}})
    version3 = bench.protocol_settings({"settings": {"model_form_allowance": True, "converged_step": True}})
    assert (version1.model_form_allowance, version1.converged_step) == (False, False)
    assert (version2.model_form_allowance, version2.converged_step) == (True, False)
    assert (version3.model_form_allowance, version3.converged_step) == (True, True)


def test_protocol_blocks_run_resume_and_print_side_by_side(tmp_path, monkeypatch, capsys):
    bench = _bench()
    calls = []

    def fake(case, settings=None):
        calls.append(case.case_id)
        return _fake_run_case(case)

    monkeypatch.setattr(selfcheck, "run_case", fake)
    protocol = tmp_path / "protocol.yaml"
    frozen = bench.freeze(protocol, development=[11], evaluation=[5201])
    frozen["selfcheck"].update(concepts=["htls"], sensors=["realistic"], kinds=["none", "out_of_catalogue"],
                               none_per_set=2)
    protocol.write_text(bench.yaml.safe_dump(frozen), encoding="utf-8")
    out = tmp_path / "results"
    bench.protocol_main(protocol, "development", out_dir=out, chunk="1/2")
    n_part = len(calls)
    bench.protocol_main(protocol, "development", out_dir=out)
    n_cases = 2 + sum(v.family is None for v in VARIANTS.values())
    assert n_part == n_cases // 2 and len(calls) == n_cases                 # the part was not diagnosed again
    cached = list((out / "development").glob("*/seed11/*.json"))
    assert len(cached) == n_cases and cached[0].parent.parent.name == frozen["sources"]["sha256"][:12]
    # each run recorded its libraries: the part's cases belong to the first, the rest to the second
    by_run = bench.cases_by_environment(cached[0].parent)
    assert [len(files) for _, files in by_run] == [n_part, n_cases - n_part]
    assert all(libraries == bench.library_versions() for libraries, _ in by_run)
    bench.protocol_main(protocol, "evaluation", out_dir=out)
    text = capsys.readouterr().out
    assert "[[Blocks]] (seeds development: 11; evaluation: 5201)" in text
    assert json.loads((out / "evaluation.json").read_text())["settings"]["seeds"] == [5201]


def _evaluated_then_refactored(bench, tmp_path, monkeypatch):
    """A protocol frozen on a copy of the sources, its (small, faked) evaluation block run, then a
    source file changed without changing a number. Returns (root, protocol file, frozen, outcomes)."""
    root = _copy_of_the_sources(bench, tmp_path / "repo")
    protocol = tmp_path / "protocol.yaml"
    frozen = bench.freeze(protocol, root=root, development=[11], evaluation=[5201])
    frozen["selfcheck"].update(concepts=["htls"], sensors=["realistic"], kinds=["none"], none_per_set=2)
    protocol.write_text(bench.yaml.safe_dump(frozen), encoding="utf-8")
    monkeypatch.setattr(selfcheck, "run_case", lambda case, settings=None: _fake_run_case(case))
    out = tmp_path / "results"
    bench.protocol_main(protocol, "evaluation", root=root, out_dir=out)
    with open(root / "ema_uq" / "gap" / "attribute.py", "a", encoding="utf-8") as fh:
        fh.write("\n# moved code, same numbers\n")
    return root, protocol, frozen, out


def test_a_refactor_is_attested_only_when_stored_outcomes_rerun_identically(tmp_path, monkeypatch):
    bench = _bench()
    root, protocol, frozen, out = _evaluated_then_refactored(bench, tmp_path, monkeypatch)
    assert bench.check_sources(bench.load_protocol(protocol), root=root) is not None

    def shifted(case, settings=None):
        outcome = _fake_run_case(case)
        outcome.gap_before = outcome.gap_before * (1 + 1e-12) + 1e-15      # one value, barely off
        return outcome

    monkeypatch.setattr(bench, "run_case", shifted)
    with pytest.raises(SystemExit, match="alters results"):
        bench.attest_equivalent(protocol, 2, out_dir=out, root=root)
    assert bench.check_sources(bench.load_protocol(protocol), root=root) is not None   # nothing recorded

    monkeypatch.setattr(bench, "run_case", lambda case, settings=None: _fake_run_case(case))
    entry = bench.attest_equivalent(protocol, 2, out_dir=out, root=root)
    assert len(entry["cases_rerun"]) == 2 and entry["values_identical"] > 10
    # the stored numbers carry the libraries' arithmetic: both the freeze and the attestation say which
    assert entry["libraries"] == bench.library_versions() == bench.load_protocol(protocol)["libraries"]
    assert bench._libraries_note(bench.load_protocol(protocol)) == ""
    assert "no library versions" in bench._libraries_note({"sources": {}})
    assert "re-run both sources" in bench._libraries_note({"sources": {}, "libraries": {"numpy": "1.0"}})
    attested = bench.load_protocol(protocol)
    assert attested["sources"]["sha256"] == frozen["sources"]["sha256"]              # the frozen hash stays
    assert bench.check_sources(attested, root=root) is None
    monkeypatch.setattr(selfcheck, "run_case", lambda *a, **k: pytest.fail("diagnosed a stored case again"))
    bench.protocol_main(protocol, "evaluation", root=root, out_dir=out)              # continues the same outcomes


def test_an_attestation_against_a_revision_compares_both_sources_run_on_this_machine(tmp_path, monkeypatch):
    """Stored outcomes carry the last digits of the setup that computed them; --reference compares
    the current sources with an accepted revision run here instead, and refuses a revision the
    protocol does not accept or any value that differs between the two."""
    bench = _bench()
    accepted = _copy_of_the_sources(bench, tmp_path / "accepted")        # what a checkout of the revision holds
    root, protocol, frozen, out = _evaluated_then_refactored(bench, tmp_path, monkeypatch)

    def here(case, settings=None):          # this setup rounds differently from the one that stored them
        outcome = _fake_run_case(case)
        outcome.gap_before = outcome.gap_before * (1 + 1e-9)
        return outcome

    monkeypatch.setattr(bench, "run_case", here)
    with pytest.raises(SystemExit, match="alters results.*--reference REVISION"):
        bench.attest_equivalent(protocol, 2, out_dir=out, root=root)

    trees = {"accepted": accepted, "other": _copy_of_the_sources(bench, tmp_path / "other")}
    with open(trees["other"] / "ema_uq" / "gap" / "verdict.py", "a", encoding="utf-8") as fh:
        fh.write("\n# another method\n")

    @contextlib.contextmanager
    def checkout(revision, root=None):
        yield trees[revision], revision.ljust(40, "0")

    def reference_run(runner):
        def run(tree, stored_file, protocol_path):
            stored = json.loads(Path(stored_file).read_text(encoding="utf-8"))
            return json.loads(json.dumps(runner(selfcheck.CaseOutcome.from_json(stored).case).to_json()))
        return run

    monkeypatch.setattr(bench, "_checkout", checkout)
    monkeypatch.setattr(bench, "_reference_outcome", reference_run(here))
    with pytest.raises(SystemExit, match="does not accept"):
        bench.attest_equivalent(protocol, 2, out_dir=out, root=root, reference="other")
    monkeypatch.setattr(bench, "_reference_outcome", reference_run(_fake_run_case))   # the code changed the numbers
    with pytest.raises(SystemExit, match="differs from revision accepted0"):
        bench.attest_equivalent(protocol, 2, out_dir=out, root=root, reference="accepted")
    assert bench.check_sources(bench.load_protocol(protocol), root=root) is not None    # nothing recorded
    monkeypatch.setattr(bench, "_reference_outcome", reference_run(here))
    entry = bench.attest_equivalent(protocol, 2, out_dir=out, root=root, reference="accepted")
    assert entry["against_revision"] == {"revision": "accepted".ljust(40, "0"), "sha256": frozen["sources"]["sha256"]}
    assert len(entry["cases_rerun"]) == 2 and entry["values_identical"] > 10
    assert bench.check_sources(bench.load_protocol(protocol), root=root) is None


def test_a_checkout_is_a_temporary_worktree_of_the_revision(tmp_path):
    bench = _bench()
    repo = tmp_path / "repo"
    repo.mkdir()
    git = ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run(git[:3] + ["init", "-q"], check=True)
    (repo / "a.txt").write_text("one", encoding="utf-8")
    subprocess.run(git + ["add", "a.txt"], check=True)
    subprocess.run(git + ["commit", "-qm", "one"], check=True)
    (repo / "a.txt").write_text("two", encoding="utf-8")
    with bench._checkout("HEAD", repo) as (tree, commit):
        assert (tree / "a.txt").read_text(encoding="utf-8") == "one" and len(commit) == 40
    assert not tree.exists()
    with pytest.raises(SystemExit, match="git rev-parse"):
        with bench._checkout("no-such-revision", repo):
            pass
    # a checkout that cannot diagnose says so in one line
    with pytest.raises(SystemExit, match="could not diagnose x.json"):
        bench._reference_outcome(tmp_path, tmp_path / "x.json", tmp_path / "p.yaml")


def test_unseen_cases_are_new_records_of_the_unseen_variants_only():
    from ema_uq.gap.variants import UNSEEN_VARIANTS

    unseen = selfcheck.unseen_cases(5301)
    inside = [v for v, var in UNSEEN_VARIANTS.items() if var.family is not None]
    assert len(unseen) == 2 * 2 * (len(UNSEEN_VARIANTS) + len(inside))
    assert {c.variant for c in unseen} == set(UNSEEN_VARIANTS)
    assert {c.kind for c in unseen if c.family is None} == {"out_of_catalogue"}
    for case in (c for c in unseen if c.kind == "left_out"):
        assert case.variant in inside and case.family == UNSEEN_VARIANTS[case.variant].family
        assert not set(case.candidates) & set(selfcheck.catalogue_families(case.concept)[case.family])
    # no record of the self-check is drawn again: every case seed differs from those of its cases
    assert not {c.seed for c in unseen} & {c.seed for c in selfcheck.build_cases(seed=5301)}
    assert len({c.seed for c in unseen}) == len(unseen)
    assert not {c.variant for c in selfcheck.build_cases(seed=5301)} & set(UNSEEN_VARIANTS)


def test_the_second_unseen_set_has_cases_of_its_own():
    from ema_uq.gap.variant_catalogue import UNSEEN_VARIANTS, UNSEEN_VARIANTS_2

    second = selfcheck.unseen_cases(5401, variant_set="UNSEEN_VARIANTS_2")
    inside = [v for v, var in UNSEEN_VARIANTS_2.items() if var.family is not None]
    assert len(second) == 2 * 2 * (len(UNSEEN_VARIANTS_2) + len(inside))
    assert {c.variant for c in second} == set(UNSEEN_VARIANTS_2)
    assert {c.kind for c in second if c.family is None} == {"out_of_catalogue"}
    for case in (c for c in second if c.kind == "left_out"):
        assert case.variant in inside and case.family == UNSEEN_VARIANTS_2[case.variant].family
        assert not set(case.candidates) & set(selfcheck.catalogue_families(case.concept)[case.family])
    # no record repeats one of the self-check's or of the first set, at this seed or the first set's
    for seed in (5401, 5301):
        others = selfcheck.build_cases(seed=seed) + selfcheck.unseen_cases(seed)
        mine = selfcheck.unseen_cases(seed, variant_set="UNSEEN_VARIANTS_2")
        assert not {c.seed for c in mine} & {c.seed for c in others}
    assert len({c.seed for c in second}) == len(second)
    assert not {c.variant for c in selfcheck.build_cases(seed=5401)} & set(UNSEEN_VARIANTS_2)
    # the first set stays the default
    first = selfcheck.unseen_cases(5301)
    assert first == selfcheck.unseen_cases(5301, variant_set="UNSEEN_VARIANTS")
    assert {c.variant for c in first} == set(UNSEEN_VARIANTS)
    with pytest.raises(selfcheck.SelfCheckError, match="unknown unseen variant set") as info:
        selfcheck.unseen_cases(5401, variant_set="UNSEEN_VARIANTS_9")
    assert "\n" not in str(info.value)


def test_the_third_unseen_set_has_cases_of_its_own():
    from ema_uq.gap.variant_catalogue import UNSEEN_VARIANTS_3

    third = selfcheck.unseen_cases(5601, variant_set="UNSEEN_VARIANTS_3")
    inside = [v for v, var in UNSEEN_VARIANTS_3.items() if var.family is not None]
    assert len(third) == 2 * 2 * (len(UNSEEN_VARIANTS_3) + len(inside)) == 36
    assert {c.variant for c in third} == set(UNSEEN_VARIANTS_3)
    assert {c.kind for c in third if c.family is None} == {"out_of_catalogue"}
    assert {c.kind for c in third if c.family is not None} == {"effect", "left_out"}
    for case in (c for c in third if c.kind == "left_out"):
        assert case.variant in inside and case.family == UNSEEN_VARIANTS_3[case.variant].family
        assert not set(case.candidates) & set(selfcheck.catalogue_families(case.concept)[case.family])
    # no record repeats one of the self-check's or of an earlier unseen set, at this seed or theirs
    for seed in (5601, 5602, 5401, 5301):
        others = (selfcheck.build_cases(seed=seed) + selfcheck.unseen_cases(seed)
                  + selfcheck.unseen_cases(seed, variant_set="UNSEEN_VARIANTS_2"))
        mine = selfcheck.unseen_cases(seed, variant_set="UNSEEN_VARIANTS_3")
        assert not {c.seed for c in mine} & {c.seed for c in others}
    assert len({c.seed for c in third}) == len(third)
    assert not {c.variant for c in selfcheck.build_cases(seed=5601)} & set(UNSEEN_VARIANTS_3)
    assert selfcheck.UNSEEN_SLOTS["UNSEEN_VARIANTS_3"] == (700, 800)


def _unseen_script(monkeypatch):
    """benchmarks/gap_unseen.py as a module; it imports its sibling benchmarks/gap.py as ``gap``,
    as when it is run."""
    import sys

    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    monkeypatch.setitem(sys.modules, "gap", _bench())
    spec = importlib.util.spec_from_file_location("gap_unseen_bench", ROOT / "benchmarks" / "gap_unseen.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_paired_reference_protocol_cannot_change_the_cases(tmp_path, monkeypatch):
    path = tmp_path / "reference.yaml"
    path.write_text(yaml.safe_dump({"cases_from": "benchmarks/gap_unseen3.yaml", "seeds": [1],
                                    "method_protocol": "benchmarks/gap_protocol_v4.yaml", "results": "x"}))
    with pytest.raises(SystemExit, match="sets only method_protocol and results, not \\['seeds'\\]"):
        _unseen_script(monkeypatch).load_unseen_protocol(path)
    path.write_text(yaml.safe_dump({"cases_from": "benchmarks/gap_unseen3.yaml",
                                    "method_protocol": "benchmarks/gap_protocol_v4.yaml"}))
    with pytest.raises(SystemExit, match="and both; \\['results'\\] is missing"):
        _unseen_script(monkeypatch).load_unseen_protocol(path)


def test_the_third_unseen_protocol_lists_its_cases(monkeypatch):
    with open(ROOT / "benchmarks" / "gap_unseen3.yaml", encoding="utf-8") as fh:
        protocol = yaml.safe_load(fh)
    from ema_uq.gap.variant_catalogue import UNSEEN_VARIANTS_3

    assert protocol["variant_set"] == "UNSEEN_VARIANTS_3" and protocol["seeds"] == [5601, 5602]
    # written for version 5, never frozen; run on the frozen version 7, version 4 as the paired reference
    assert protocol["method_protocol"] == "benchmarks/gap_protocol_v7.yaml"
    assert protocol["results"] == "benchmarks/protocol_outcomes/method7/unseen3"
    reference = _unseen_script(monkeypatch).load_unseen_protocol(ROOT / "benchmarks" / "gap_unseen3_v4.yaml")
    assert reference["method_protocol"] == "benchmarks/gap_protocol_v4.yaml"
    assert reference["results"] == "benchmarks/protocol_outcomes/method4/unseen3"
    assert {k: v for k, v in reference.items() if k not in ("method_protocol", "results")} == {
        k: v for k, v in protocol.items() if k not in ("method_protocol", "results")}
    written = {k: v.family for k, v in UNSEEN_VARIANTS_3.items()}
    assert {k: v["family"] for k, v in protocol["variants"].items()} == written
    assert {k for k, v in protocol["variants"].items() if v.get("left_out_too")} == {
        k for k, v in UNSEEN_VARIANTS_3.items() if v.family is not None}
    for seed in protocol["seeds"]:
        cases = selfcheck.unseen_cases(seed, protocol["concepts"], protocol["sensors"], protocol["variant_set"])
        assert len(cases) == protocol["n_cases_per_seed"]
        assert {c.variant for c in cases if c.kind == "left_out"} == {
            k for k, v in protocol["variants"].items() if v.get("left_out_too")}


@pytest.mark.parametrize("protocol_file, variant", [("gap_unseen.yaml", "stribeck_asymmetric"),
                                                    ("gap_unseen2.yaml", "ujoint_swivel"),
                                                    ("gap_unseen3.yaml", "stribeck_dwell"),
                                                    ("gap_unseen3_v4.yaml", "stribeck_dwell")])
def test_the_unseen_protocol_describes_the_cases_it_runs(tmp_path, monkeypatch, protocol_file, variant):
    module = _unseen_script(monkeypatch)
    protocol = module.load_unseen_protocol(ROOT / "benchmarks" / protocol_file)
    variant_set = protocol.get("variant_set", module.DEFAULT_VARIANT_SET)
    cases = selfcheck.unseen_cases(int(protocol["seeds"][0]), protocol["concepts"], protocol["sensors"], variant_set)
    assert len(cases) == protocol["n_cases_per_seed"]
    assert {c.variant for c in cases} == set(protocol["variants"])
    # a protocol that no longer names the code's variants and families stops the run
    changed = dict(protocol, variants={**protocol["variants"], variant: {"family": "backlash"}})
    path = tmp_path / "unseen.yaml"
    path.write_text(yaml.safe_dump(changed), encoding="utf-8")
    with pytest.raises(SystemExit, match="no longer describes the cases"):
        module.load_unseen_protocol(path)
    path.write_text(yaml.safe_dump(dict(protocol, variant_set="UNSEEN_VARIANTS_9")), encoding="utf-8")
    with pytest.raises(SystemExit, match="names the variant set"):
        module.load_unseen_protocol(path)


# --------------------------------------------------------------------------------------
# two versions on the same block (benchmarks/gap_paired.py)
# --------------------------------------------------------------------------------------
def _paired_script(monkeypatch):
    import sys

    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    monkeypatch.setitem(sys.modules, "gap", _bench())
    spec = importlib.util.spec_from_file_location("gap_paired_bench", ROOT / "benchmarks" / "gap_paired.py")
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, module)     # its dataclass looks its module up there
    spec.loader.exec_module(module)
    return module


def _block(top1_right=True, left_out="unexplained"):
    """Eight cases: two in catalogue, two left out, one out of catalogue, three without an effect."""
    return selfcheck.SelfCheckResult([
        _outcome("effect", "stribeck", "effect", "stribeck", index=0),
        _outcome("effect", "backlash", "effect", "backlash" if top1_right else "stribeck", "low", index=1),
        _outcome("left_out", "backlash", "unexplained", confidence="low", index=2),
        _outcome("left_out", "stribeck", left_out, confidence="low", index=3),
        _outcome("out_of_catalogue", None, "unexplained", confidence="low", index=4),
        *[_outcome("none", None, "none", index=5 + i) for i in range(3)]], seed=1, quick=False, wall_time_s=1.0)


def test_the_paired_rule_switches_only_when_the_challenger_loses_nothing_on_the_same_cases(monkeypatch):
    paired = _paired_script(monkeypatch)
    same = paired.read_rule(_block(), _block(), n_block=8)
    assert same.complete and same.switch and not same.differing()
    # one in-catalogue record fewer: the rule fails, and the differing case is listed
    worse = paired.read_rule(_block(), _block(top1_right=False), n_block=8)
    assert not worse.switch and [c[3] for c in worse.conditions][0] is False
    assert len(worse.differing()) == 1 and "htls/full/backlash_v/1" in worse.differing()[0]
    # a left-out record no longer flagged: both the paired count and the 0.85 floor fail
    unflagged = paired.read_rule(_block(), _block(left_out="none"), n_block=8)
    failed = [label for label, *_, held in unflagged.conditions if not held]
    assert failed == ["left out flagged", "challenger's left out flagged"] and not unflagged.switch
    # with one record of slack (version 10's rule) one in-catalogue record fewer passes, two do not
    assert paired.read_rule(_block(), _block(top1_right=False), n_block=8, slack=1).switch
    two_fewer = _block(top1_right=False)
    two_fewer.outcomes[0] = _outcome("effect", "stribeck", "effect", "backlash", "low", index=0)
    assert not paired.read_rule(_block(), two_fewer, n_block=8, slack=1).switch
    # the challenger's own bounds get no slack: a left-out record unflagged still fails its 0.85 floor
    assert not paired.read_rule(_block(), _block(left_out="none"), n_block=8, slack=1).switch
    # the incumbent doing worse on the same cases does not stop the challenger
    assert paired.read_rule(_block(top1_right=False), _block(), n_block=8).switch
    # a block not yet complete decides nothing, however the counts stand
    partial = paired.read_rule(_block(), _block(), n_block=176)
    assert not partial.complete and not partial.switch
    # until then it says how far each run is, and shows figures only when asked
    assert "has run 8 and the challenger 8 of its 176 cases" in partial.summary()
    assert "top-1" not in partial.summary()
    assert "PARTIAL (8 of 176 cases)" in partial.summary(partial_figures=True)
    assert "not decided" in partial.summary(partial_figures=True)


# --------------------------------------------------------------------------------------
# a development run against the incumbent's outcomes of the same records (benchmarks/gap_development.py)
# --------------------------------------------------------------------------------------
def _development_script(monkeypatch):
    spec = importlib.util.spec_from_file_location("gap_development_bench", ROOT / "benchmarks" / "gap_development.py")
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, module)     # its dataclass looks its module up there
    spec.loader.exec_module(module)
    return module


def _write_outcomes(folder: Path, result) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for o in result.outcomes:
        (folder / f"{o.case.case_id.replace('/', '__')}.json").write_text(json.dumps(o.to_json()))
    return folder


def test_the_development_rule_reads_each_condition_on_the_shared_records(monkeypatch, tmp_path):
    development = _development_script(monkeypatch)
    read = development.read_outcomes
    incumbent = read(_write_outcomes(tmp_path / "v4", _block()))
    same = development.read_rule(incumbent, read(_write_outcomes(tmp_path / "same", _block())))
    assert same.complete and same.passes and not same.differing() and same.moved() == 0
    # one left-out record fewer flagged is within the rule's slack; one in-catalogue hit fewer is not
    slack = development.read_rule(incumbent, read(_write_outcomes(tmp_path / "slack", _block(left_out="none"))))
    assert slack.passes and [held for *_, held in slack.rows] == [True] * 5
    worse = development.read_rule(incumbent, read(_write_outcomes(tmp_path / "worse", _block(top1_right=False))))
    assert [held for *_, held in worse.rows] == [False, True, True, True, True] and not worse.passes
    assert len(worse.differing()) == 1 and "htls/full/backlash_v/1" in worse.differing()[0]
    # a no-effect record naming a family, or a wrong family named with high confidence, fails outright
    named = _block()
    named.outcomes[5] = _outcome("none", None, "effect", "stribeck", index=5)
    named.outcomes[4] = _outcome("out_of_catalogue", None, "effect", "stribeck", "high", index=4)
    failed = development.read_rule(incumbent, read(_write_outcomes(tmp_path / "named", named)))
    assert [label for label, *_, held in failed.rows if not held] == [
        "(c) out of catalogue named a family", "(d) no-effect records naming a family",
        "(e) wrong family named with high confidence"]
    # the non-inferiority rule (version 10) gives one record of slack on every count, and no more
    lenient = development.read_rule(incumbent, read(tmp_path / "named"), "non-inferiority")
    assert lenient.passes and [held for *_, held in lenient.rows] == [True] * 5
    assert development.read_rule(incumbent, read(tmp_path / "worse"), "non-inferiority").passes
    twice = _block()
    twice.outcomes[5] = _outcome("none", None, "effect", "stribeck", index=5)
    twice.outcomes[6] = _outcome("none", None, "effect", "stribeck", index=6)
    two = development.read_rule(incumbent, read(_write_outcomes(tmp_path / "twice", twice)), "non-inferiority")
    assert [label for label, *_, held in two.rows if not held] == ["(d) no-effect records naming a family"]
    assert not two.passes
    # a run not yet complete decides nothing; a case the incumbent lacks stops the reading
    partial = _block()
    partial.outcomes = partial.outcomes[:5]
    reading = development.read_rule(incumbent, read(_write_outcomes(tmp_path / "partial", partial)))
    assert not reading.complete and not reading.passes and "PARTIAL (5 of the incumbent's 8 cases)" in reading.summary()
    stray = _block()
    stray.outcomes.append(_outcome("none", None, "none", index=99))
    with pytest.raises(SystemExit, match="not in the incumbent's folder"):
        development.read_rule(incumbent, read(_write_outcomes(tmp_path / "stray", stray)))
    with pytest.raises(SystemExit, match="no such folder"):
        read(tmp_path / "missing")


def test_the_paired_reading_needs_the_same_block_and_only_its_cases(monkeypatch, tmp_path):
    paired = _paired_script(monkeypatch)
    protocol = yaml.safe_load((ROOT / "benchmarks" / "gap_protocol_v7.yaml").read_text(encoding="utf-8"))
    protocol["blocks"]["evaluation"]["seeds"] = [9001]
    files = {}
    for name, seeds in (("a", [9001]), ("b", [9001]), ("c", [9002])):
        files[name] = tmp_path / f"{name}.yaml"
        files[name].write_text(yaml.safe_dump({**protocol, "blocks": {**protocol["blocks"], "evaluation": {
            "seeds": seeds, "spent": []}}}))
    with pytest.raises(SystemExit, match="different evaluation blocks"):
        paired.compare((files["a"], tmp_path / "ra"), (files["c"], tmp_path / "rc"))
    cases = [c for c in selfcheck.build_cases(seed=9001, none_per_set=16)][:3]
    for folder, verdicts in (("ra", ("none", "none", "none")), ("rb", ("none", "unexplained", None))):
        for case, verdict in zip(cases, verdicts):
            if verdict is None:
                continue
            out = tmp_path / folder / "evaluation" / "abc" / "seed9001" / f"{case.case_id.replace('/', '__')}.json"
            out.parent.mkdir(parents=True, exist_ok=True)
            # each version offers its own candidates; the record is what must be the same
            offered = case if folder == "ra" else dataclasses.replace(case, candidates=("stribeck",))
            outcome = selfcheck.CaseOutcome(offered, verdict, None, None, "low", float("nan"), float("nan"), None,
                                            0.02, 0.02, {}, 1.0)
            out.write_text(json.dumps(outcome.to_json()))
    reading = paired.compare((files["a"], tmp_path / "ra"), (files["b"], tmp_path / "rb"))
    assert len(reading.incumbent.outcomes) == 2 and not reading.complete and reading.n_block == 176
    assert reading.runs == (3, 2) and "incumbent has run 3 and the challenger 2" in reading.summary()
    # an outcome of another block in a results folder stops the reading
    stray = selfcheck.build_cases(seed=9002, none_per_set=16)[3]
    (tmp_path / "rb" / "evaluation" / "abc" / "seed9001" / "stray.json").write_text(json.dumps(
        selfcheck.CaseOutcome(stray, "none", None, None, "low", float("nan"), float("nan"), None, 0.02, 0.02, {},
                              1.0).to_json()))
    with pytest.raises(SystemExit, match="not cases of the block"):
        paired.compare((files["a"], tmp_path / "ra"), (files["b"], tmp_path / "rb"))


def test_a_block_folder_says_which_library_versions_diagnosed_which_cases(monkeypatch, tmp_path):
    bench = _bench()
    folder = tmp_path / "seed9001"
    folder.mkdir()
    (folder / "a.json").write_text("{}")                        # stored before runs recorded anything
    first = {"python": "3.11.7", "numpy": "2.4.6", "scipy": "1.17.1", "numba": "0.68.1"}
    second = {**first, "numpy": "2.5.0"}
    monkeypatch.setattr(bench, "library_versions", lambda: first)
    assert bench.record_environment(folder) is None
    for name in ("b.json", "c.json"):
        (folder / name).write_text("{}")
    assert bench.record_environment(folder) is None             # the same libraries: nothing to say
    (folder / "d.json").write_text("{}")
    monkeypatch.setattr(bench, "library_versions", lambda: second)
    note = bench.record_environment(folder)
    assert "2.4.6" in note and "2.5.0" in note
    (folder / "e.json").write_text("{}")
    assert bench.cases_by_environment(folder) == [(None, ["a.json"]), (first, ["b.json", "c.json"]),
                                                  (first, ["d.json"]), (second, ["e.json"])]
    # the paired reading adds them up per version and says when the block spans environments
    paired = _paired_script(monkeypatch)
    results = tmp_path / "results"
    (results / "evaluation" / "abc").mkdir(parents=True)
    shutil.copytree(folder, results / "evaluation" / "abc" / "seed9001")
    counts = paired.environments(results)
    assert counts == [(None, 1), (first, 3), (second, 1)]
    reading = dataclasses.replace(paired.read_rule(_block(), _block(), n_block=176), environments=(counts, counts))
    assert "incumbent: 3 cases, python 3.11.7, numpy 2.4.6" in reading.summary()
    assert "spans 2 library environments" in reading.summary()
    one = dataclasses.replace(reading, environments=([(first, 8)], [(None, 2), (first, 6)]))
    assert "spans" not in one.summary() and "2 cases, stored before runs recorded" in one.summary()
    # a line that is not a record stops the reading, naming it
    with open(folder / bench.ENVIRONMENTS, "a") as fh:
        fh.write("not json\n")
    with pytest.raises(SystemExit, match="line 4: not an environment record"):
        bench.cases_by_environment(folder)


@pytest.mark.parametrize("block, version", [(5209, 4), (5209, 7), (5210, 4), (5210, 9), (5210, 10)])
def test_the_paired_block_protocols_freeze_their_versions_method_on_a_block_no_protocol_has_run(block, version):
    bench = _bench()
    paired = bench.load_protocol(ROOT / "benchmarks" / f"gap_protocol_paired{block}_v{version}.yaml")
    incumbent = bench.load_protocol(ROOT / "benchmarks" / f"gap_protocol_paired{block}_v4.yaml")
    assert paired["method_version"] == version
    assert bench.protocol_settings(paired) == bench.method_settings(version)
    own = ROOT / "benchmarks" / f"gap_protocol_v{version}.yaml"
    if own.is_file():       # a version frozen before on a block of its own: the same method
        own = bench.load_protocol(own)
        assert bench.protocol_settings(paired) == bench.protocol_settings(own)
        assert paired["catalogue"] == own["catalogue"] and paired["thresholds"] == own["thresholds"]
    # the pair differs in its method only: the same self-check, targets and evaluation block
    assert paired["selfcheck"] == incumbent["selfcheck"]
    assert paired["blocks"]["evaluation"]["seeds"] == [block]
    # no other protocol has used the block, as an evaluation block, spent or for development
    for other in (ROOT / "benchmarks").glob("gap_protocol*.yaml"):
        if f"paired{block}" in other.name:
            continue
        blocks = bench.load_protocol(other)["blocks"]
        used = set(blocks["evaluation"]["seeds"]) | {s for b in blocks["evaluation"].get("spent") or [] for s in b}
        assert block not in used | set(blocks["development"]["seeds"]), other.name
