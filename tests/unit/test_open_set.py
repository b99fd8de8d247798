"""The open-set verdict: family probabilities, the margin, and the cells a candidate leaves."""
import json

import numpy as np
import pytest

from ema_uq.gap.localize import ResidualRecord
from ema_uq.gap.result import CandidateScore
from ema_uq.gap.strategy import (DEFAULT_METHOD_VERSION, METHOD_VERSIONS, DiagnosisSettings, Thresholds,
                                 method_switches)
from ema_uq.gap.structure import (CellEnergy, StructureSettings, cell_energies, cell_masks, stroke_bins,
                                  structure_left, where_along_stroke, where_left)
from ema_uq.gap.verdict import (MARGIN_EVIDENCE, effective_sample_fraction, family_probabilities, verdict,
                                within_margin)
from ema_uq.models import get_model


class Clean:
    structured = False


def _row(effect, family, delta_bic, gain, shrink=0.9):
    return CandidateScore(effect, delta_bic + gain, 1.0, 1.0 - shrink, shrink, delta_bic, delta_bic, gain, 0.5, 1,
                          selection_shrink=shrink, family=family)


# --- effective sample fraction ------------------------------------------------------------
def test_effective_sample_fraction_is_one_for_white_noise_and_falls_with_autocorrelation():
    rng = np.random.default_rng(3)
    white = rng.normal(size=(20000, 2))
    assert effective_sample_fraction([white]) == pytest.approx(1.0, abs=0.05)
    phi = 0.8
    ar = np.zeros((20000, 1))
    shocks = rng.normal(size=20000)
    for k in range(1, 20000):
        ar[k, 0] = phi * ar[k - 1, 0] + shocks[k]
    assert effective_sample_fraction([ar]) == pytest.approx((1 - phi) / (1 + phi), rel=0.2)
    with_gaps = white.copy()
    with_gaps[100:200] = np.nan                     # NaN rows (not fitted) are left out, not propagated
    assert np.isfinite(effective_sample_fraction([with_gaps]))


# --- family probabilities and the margin ---------------------------------------------------
def test_family_probabilities_pool_forms_and_keep_the_nominal_model():
    th = Thresholds()
    ranking = [_row("a1", "a", 1000.0, 0.0), _row("a2", "a", 900.0, 0.0), _row("b", "b", 990.0, 0.0)]
    p = family_probabilities(ranking, th)
    assert set(p) == {"a", "b", "none"} and sum(p.values()) == pytest.approx(1.0)
    # a's forms share a's prior: a1 alone at 1000 vs b at 990 is 2 ln B = 10, less ln 2 for the weak second form
    assert 2 * np.log(p["a"] / p["b"]) == pytest.approx(10 - 2 * np.log(2), abs=1e-6)
    assert within_margin(p) == ["a", "b"]
    # tempering by the effective-sample fraction shrinks every log ratio alike
    p_t = family_probabilities(ranking, th, tempering=0.1)
    assert 2 * np.log(p_t["a"] / p_t["b"]) < 2 * np.log(p["a"] / p["b"])
    assert p_t["none"] > p["none"]


def test_a_family_is_named_only_when_it_wins_by_the_margin_and_leaves_no_structure():
    th = Thresholds()
    clear = [_row("play", "backlash", 3000.0, 2000.0), _row("drag", "friction", 600.0, 100.0)]
    assert verdict(th, clear, True, True, Clean(), Clean(), left={}).as_tuple() == ("effect", "play", "high")
    # the same winner leaving structure in a cell is not the cause (or not all of it)
    left = verdict(th, clear, True, True, Clean(), Clean(), left={"play": ["a cell"]})
    assert left.verdict == "unexplained" and left.effect is None and "leaves structure" in left.reason
    # two families within the margin, one of them clean: ambiguous, both reported
    close = [_row("play", "backlash", 3000.0, 2000.0), _row("drag", "friction", 2998.0, 2000.0)]
    amb = verdict(th, close, True, True, Clean(), Clean(), left={})
    assert amb.verdict == "ambiguous" and amb.contenders == ["backlash", "friction"]
    # ... and both leaving structure: unexplained
    both = verdict(th, close, True, True, Clean(), Clean(), left={"play": ["x"], "drag": ["y"]})
    assert both.verdict == "unexplained"
    # evidence so tempered that the nominal model is within the margin: nothing is named
    p = family_probabilities(clear, th, tempering=MARGIN_EVIDENCE / 6000.0)
    assert "none" in within_margin(p)
    weak = verdict(th, clear, True, True, Clean(), Clean(), probabilities=p, left={})
    assert weak.verdict == "unexplained" and "nominal" in weak.reason


def test_without_a_passing_candidate_the_verdict_is_none_or_unexplained_as_before():
    th = Thresholds()
    fails_held_out = [_row("ripple", "ripple", 525.0, -20.0, shrink=0.0)]
    assert verdict(th, fails_held_out, False, False, Clean(), Clean()).as_tuple() == ("unexplained", None, "high")
    assert verdict(th, [_row("ripple", "ripple", -0.8, 3.0)], False, False, Clean(), Clean()).verdict == "none"


# --- cells ---------------------------------------------------------------------------------
def _cell(name, energy, sd=1.0, kind="mask"):
    return CellEnergy(name, kind, energy, sd, 100)


def test_a_cell_the_candidate_did_not_close_is_left_and_reported_where():
    before = {"all": _cell("all", 100.0, kind="all"), "stroke:1/4": _cell("stroke:1/4", 60.0),
              "stroke:2/4": _cell("stroke:2/4", 40.0)}
    # the candidate closes stroke 2 but leaves most of stroke 1
    after = {"all": _cell("all", 45.0, kind="all"), "stroke:1/4": _cell("stroke:1/4", 40.0),
             "stroke:2/4": _cell("stroke:2/4", 2.0)}
    left = structure_left(before, after)
    assert [c.name for c in left] == ["stroke:1/4"]
    assert left[0].share == pytest.approx(0.4)
    assert "stroke" in where_left(left) and "holds 40%" in where_left(left)["stroke"][0]
    assert json.loads(json.dumps(left[0].to_json()))["name"] == "stroke:1/4"
    # the cause closes every cell: nothing left
    closed = {"all": _cell("all", 3.0, kind="all"), "stroke:1/4": _cell("stroke:1/4", 2.0),
              "stroke:2/4": _cell("stroke:2/4", 1.0)}
    assert structure_left(before, closed) == []
    # what the healthy level (a replicate ceiling) leaves anyway is not asked of the candidate
    floor = {"all": _cell("all", 40.0, kind="all"), "stroke:1/4": _cell("stroke:1/4", 38.0),
             "stroke:2/4": _cell("stroke:2/4", 2.0)}
    assert structure_left(before, after, floor) == []
    # a small or insignificant remainder is no structure
    assert structure_left(before, after, settings=StructureSettings(z_cell=50.0)) == []
    assert structure_left(before, after, settings=StructureSettings(min_share=0.5)) == []


def _records(residual, y1, dt=0.01):
    n = residual.shape[0]
    t = np.arange(n) * dt
    model = get_model("htls")
    outputs = np.zeros((n, len(model.outputs)))
    outputs[:, model.outputs.index("y1")] = y1
    return [ResidualRecord("r", t, np.zeros((n, 4)), residual, np.zeros_like(residual), outputs)], model


def test_a_stroke_localised_residual_shows_in_its_stroke_cell_and_a_periodic_one_in_a_band():
    rng = np.random.default_rng(5)
    n = 6000
    y1 = 0.05 * np.sin(2 * np.pi * np.arange(n) / 3000.0)          # two strokes out and back
    noise = 0.1 * rng.normal(size=(n, 2))
    local = noise.copy()
    local[y1 > np.quantile(y1, 0.75), 0] += 0.2                    # error on the outer quarter of the stroke
    records, model = _records(local, y1)
    masks = cell_masks(records, model)
    assert {"stroke:1/4", "stroke:4/4", "direction:extend", "direction:retract"} <= set(masks)
    cells = cell_energies(records, ["a", "b"], np.ones(2), masks)
    strokes = {k: cells[k].z for k in cells if k.startswith("stroke")}
    assert max(strokes, key=strokes.get) == "stroke:4/4" and strokes["stroke:4/4"] > 20
    assert abs(strokes["stroke:2/4"]) < 5
    # a ripple at a fifth of the sample rate: the top band of its channel, not the others
    ripple = noise.copy()
    ripple[:, 1] += 0.1 * np.sin(2 * np.pi * 0.2 * np.arange(n))
    records, model = _records(ripple, y1)
    cells = cell_energies(records, ["a", "b"], np.ones(2), cell_masks(records, model))
    assert cells["band:b:0.1-0.5fs"].z > 10
    assert abs(cells["band:a:0.1-0.5fs"].z) < 5 and abs(cells["band:b:0-0.02fs"].z) < 5


def test_where_along_the_stroke_names_a_bin_that_holds_the_gap_and_not_a_gap_spread_along_it():
    rng = np.random.default_rng(6)
    n = 6000
    y1 = 0.05 * np.sin(2 * np.pi * np.arange(n) / 3000.0)
    noise = 0.1 * rng.normal(size=(n, 2))
    local = noise.copy()
    local[y1 > np.quantile(y1, 0.75), 1] += 0.2
    records, model = _records(local, y1)
    bins = stroke_bins(records, model)
    assert bins[0] == "y1" and bins[1][0] == pytest.approx(y1.min()) and bins[1][-1] == pytest.approx(y1.max())
    cells = cell_energies(records, ["a", "b"], np.ones(2), cell_masks(records, model))
    where = where_along_stroke(cells, None, bins, "m")
    assert len(where) == 1 and where[0].startswith(f"stroke:4/4 (y1 {bins[1][3]:.4g}-{bins[1][4]:.4g} m, holds")
    # the same error everywhere along the stroke: no bin holds twice its share
    spread = noise.copy()
    spread[:, 1] += 0.2
    records, model = _records(spread, y1)
    assert where_along_stroke(cell_energies(records, ["a", "b"], np.ones(2), cell_masks(records, model)), None) == []
    # what stands no higher than the healthy level is no place of the gap
    assert where_along_stroke(cells, cells) == []


def test_a_cell_that_only_the_candidate_filled_says_so():
    before = {"all": _cell("all", 100.0, kind="all"), "stroke:1/4": _cell("stroke:1/4", 90.0),
              "stroke:3/4": _cell("stroke:3/4", 5.0)}
    after = {"all": _cell("all", 60.0, kind="all"), "stroke:1/4": _cell("stroke:1/4", 10.0),
             "stroke:3/4": _cell("stroke:3/4", 45.0)}
    floor = {"all": _cell("all", 0.0, kind="all"), "stroke:1/4": _cell("stroke:1/4", 0.0),
             "stroke:3/4": _cell("stroke:3/4", 8.0)}
    left = structure_left(before, after, floor)
    assert [c.name for c in left] == ["stroke:3/4"]
    assert "made by the candidate" in left[0].describe() and "nan" not in left[0].describe()


# --- is the gap a model error? what the operating state predicts ---------------------------
def _state_records(residual_of, seed, n=4000):
    from ema_uq.gap.predictable import state_predictable  # noqa: F401  (import check)

    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.01
    speed = np.sin(2 * np.pi * t / (7.0 + seed % 3))
    outputs = np.column_stack([speed, np.cumsum(speed) * 0.01])
    inputs = np.column_stack([np.cos(2 * np.pi * t / 11.0), np.zeros(n)])
    residual = residual_of(speed, rng)
    return ResidualRecord("r", t, inputs, residual, np.zeros_like(residual), outputs)


def test_a_gap_the_state_predicts_is_a_model_error_and_coloured_noise_is_not():
    from ema_uq.gap.predictable import state_predictable

    def friction(speed, rng):         # a direction-dependent error: a function of the state
        return np.column_stack([0.05 * np.tanh(speed / 0.05), np.zeros_like(speed)]) + 0.02 * rng.normal(size=(speed.size, 2))

    def coloured(speed, rng):         # AR(1) sensor noise: structured, but no function of the state
        e = np.zeros((speed.size, 2))
        w = rng.normal(size=e.shape) * 0.02
        for k in range(1, speed.size):
            e[k] = 0.9 * e[k - 1] + w[k]
        return e

    spread = np.array([1.0, 1.0])
    model_error = state_predictable([_state_records(friction, 1)], [_state_records(friction, 2)], spread)
    assert model_error.share > 0.8 and model_error.z > 20
    noise = state_predictable([_state_records(coloured, 1)], [_state_records(coloured, 2)], spread)
    assert noise.share < 0.1 and noise.z < 5
    assert json.loads(json.dumps(noise.to_json()))["regressors"] == noise.regressors


def test_an_unexplained_gap_is_high_confidence_only_when_the_state_predicts_it():
    th = Thresholds()
    nothing_fits = [_row("ripple", "ripple", 5.0, -3.0, shrink=0.0)]
    assert verdict(th, nothing_fits, True, True, Clean(), Clean(), deterministic=True).confidence == "high"
    assert verdict(th, nothing_fits, True, True, Clean(), Clean(), deterministic=False).confidence == "low"
    assert verdict(th, nothing_fits, True, True, Clean(), Clean(), deterministic=None).confidence == "high"


def test_a_compound_of_two_mechanisms_is_no_candidate():
    from ema_uq.gap import GapError
    from ema_uq.gap.attribute import _catalogue
    from ema_uq.gap.selfcheck import catalogue_families

    model = get_model("htls")
    assert model.effect_catalogue["backlash_compliant"].combines == ("shaft_compliance",)
    for version in METHOD_VERSIONS:                       # the compound in no version, its parts in each
        settings = DiagnosisSettings(**method_switches(version))
        assert "backlash_compliant" not in _catalogue(model, settings)
        assert catalogue_families("htls", settings)["shaft_compliance"]
    assert "backlash_compliant" not in catalogue_families("htls")["backlash"]
    with pytest.raises(GapError, match="carry another family's mechanism"):
        _refuse_compound()


def _refuse_compound():
    from ema_uq import synthesize
    from ema_uq.experiments import deploy_retract
    from ema_uq.gap import diagnose

    data = synthesize("htls", deploy_retract().slice(0, 200), noise=0.02, seed=1)
    diagnose([data], candidates=["backlash_compliant"])


def test_the_spanning_forms_are_offered_from_method_version_4_on_the_default():
    from ema_uq import synthesize
    from ema_uq.experiments import deploy_retract
    from ema_uq.gap import GapError, diagnose
    from ema_uq.gap.attribute import _catalogue
    from ema_uq.gap.candidates import SPANNING_FORMS
    from ema_uq.gap.selfcheck import build_cases, catalogue_families, under_catalogue

    model = get_model("lths")
    version2, version4 = DiagnosisSettings(**method_switches(2)), DiagnosisSettings(**method_switches(4))
    assert not set(SPANNING_FORMS) & set(_catalogue(model, version2))
    assert set(SPANNING_FORMS) <= set(_catalogue(model, version4))
    # every version since 4 offers them, the default among them
    assert DiagnosisSettings().spanning_forms and set(SPANNING_FORMS) <= set(_catalogue(model))
    families = catalogue_families("lths", version4)
    assert families["stribeck"] == ["stribeck", "stribeck_directional"]
    assert families["sensor_delay"] == ["sensor_delay", "sensor_delay_dispersed"]
    # the cases are defined on version 2's catalogue, whatever the default
    assert catalogue_families("lths")["stribeck"] == ["stribeck"]
    # a left-out case keeps its family out and gets the other families' spanning forms under version 4
    case = next(c for c in build_cases(["lths"], seed=11, sensors=["full"], kinds=("left_out",))
                if c.family == "stribeck")
    assert under_catalogue(case, version2) is case
    wider = under_catalogue(case, version4)
    assert set(wider.candidates) - set(case.candidates) == {"load_friction_directional", "sensor_delay_dispersed"}
    default = DiagnosisSettings(**method_switches(DEFAULT_METHOD_VERSION))
    assert under_catalogue(case, None) == under_catalogue(case, default)   # None: the defaults the diagnosis runs with
    data = synthesize("lths", deploy_retract().slice(0, 200), noise=0.02, seed=1)
    with pytest.raises(GapError, match="method version 4 on; set DiagnosisSettings"):
        diagnose([data], candidates=["stribeck_directional"], settings=version2)


def test_version_5_offers_each_family_by_the_forms_that_nest_the_others():
    """Method version 5: the operating-point forms, and no form another offered form nests (the
    nesting form fits everything the nested one does, so offering both costs a refit for nothing)."""
    from ema_uq import synthesize
    from ema_uq.experiments import deploy_retract
    from ema_uq.gap import GapError, diagnose
    from ema_uq.gap.candidates import OPERATING_POINT_FORMS, offered_forms
    from ema_uq.gap.selfcheck import build_cases, catalogue_families, under_catalogue

    v5 = DiagnosisSettings(**method_switches(5))
    assert not set(OPERATING_POINT_FORMS) & set(offered_forms(get_model("htls").effect_catalogue,
                                                              DiagnosisSettings(**method_switches(4))))
    families = catalogue_families("htls", v5)
    assert families == {"backlash": ["backlash", "backlash_output"], "stribeck": ["stribeck_directional"],
                        "shaft_compliance": ["shaft_compliance_loaded"],
                        "ujoint_kinematics": ["ujoint_stations", "ujoint_stroke"],
                        "load_dependent_friction": ["load_friction_directional"],
                        "sensor_delay": ["sensor_delay_dispersed"],
                        "torque_ripple": ["torque_ripple_harmonics", "torque_ripple_loaded"]}
    # every form version 2 offers is offered by version 5 or nested in a form it offers
    offered = {n for forms in families.values() for n in forms}
    nested = {inner for n in offered for inner in get_model("htls").effect_catalogue[n].nests}
    assert {n for forms in catalogue_families("htls").values() for n in forms} <= offered | nested
    case = next(c for c in build_cases(["htls"], seed=11, sensors=["full"], kinds=("left_out",))
                if c.family == "stribeck")
    assert set(under_catalogue(case, v5).candidates) == offered - {"stribeck_directional"}
    data = synthesize("htls", deploy_retract().slice(0, 200), noise=0.02, seed=1)
    with pytest.raises(GapError, match="method version 5 on; set DiagnosisSettings"):
        diagnose([data], candidates=["ujoint_stroke"], settings=DiagnosisSettings(**method_switches(4)))
    # a nested form is left out of the offered catalogue, not refused when asked for by name
    assert "stribeck" not in offered
    longer = synthesize("htls", deploy_retract().slice(0, 1500), noise=0.02, seed=1)
    asked = diagnose([longer], candidates=["stribeck"], settings=v5)
    assert [row.effect for row in asked.ranking] == ["stribeck"]
