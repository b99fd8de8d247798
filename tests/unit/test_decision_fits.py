"""Fits at the precision a decision reads: the estimator's extrapolated stopping rule
(``Settings.decrease_tolerance``), fits that skip the identifiable combinations
(``Settings.combinations``), the gap diagnosis's ``decision_fits`` that switches both on, and the
singular start that goes straight to the fit holding the undetermined parameters."""
from __future__ import annotations

import numpy as np
import pytest

from ema_uq.experiments import deploy_retract, synthesize
from ema_uq.gap import candidates, fitting
from ema_uq.gap.strategy import DECISION_TOLERANCE, DiagnosisSettings, method_switches
from ema_uq.identify import FitProblem, IdentificationError, Settings, estimate, perturbed_start
from ema_uq.identify import estimators
from ema_uq.models import get_model

RIG = ("Omega", "y1", "y2", "I_A")


@pytest.fixture(scope="module")
def model():
    return get_model("htls")


@pytest.fixture(scope="module")
def full_problem():
    """All channels of the first 5 s of deploy-retract: regular, Gauss-Newton converges linearly."""
    return FitProblem([synthesize("htls", deploy_retract().slice(0, 500), noise=0.02, seed=1)])


@pytest.fixture(scope="module")
def rig_problem(model):
    """The rig's sensors alone: the station losses are lumped, the information at any start singular."""
    record = synthesize("htls", deploy_retract().slice(0, 500), noise=0.02, seed=1, channels=RIG)
    return FitProblem([record], parameters=model.parameters)


def own(problem: FitProblem) -> FitProblem:
    """The same problem with a prediction memo of its own: fits whose costs are compared must not
    serve each other's runs."""
    return FitProblem(list(problem.measurements), parameters=problem.parameters, channels=problem.channels)


def test_remaining_decrease_is_the_geometric_tail_of_the_last_two_decreases():
    assert estimators._remaining_decrease(4.0, 1.0) == pytest.approx(1.0 / 3.0)     # 1/4 + 1/16 + ...
    assert estimators._remaining_decrease(100.0, 1.0) == pytest.approx(1.0 / 99.0)
    assert estimators._remaining_decrease(None, 1.0) == np.inf        # one decrease gives no ratio
    assert estimators._remaining_decrease(1.0, 1.0) == np.inf         # not converging geometrically
    assert estimators._remaining_decrease(1.0, 2.0) == np.inf


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf"), "0.1", True])
def test_a_decrease_tolerance_that_is_not_a_positive_number_is_refused(bad):
    with pytest.raises(IdentificationError, match="decrease_tolerance must be a positive number"):
        Settings(decrease_tolerance=bad)


def test_decision_fits_must_be_true_or_false():
    with pytest.raises(ValueError, match="decision_fits must be true or false"):
        DiagnosisSettings(decision_fits="yes")


def test_the_extrapolated_rule_stops_earlier_within_its_tolerance_of_the_optimum(model, full_problem):
    start = perturbed_start(model.parameters, 0.3, seed=3, around=model.parameters.nominal)
    full = estimate(own(full_problem), start=start)
    lean = estimate(own(full_problem), start=start, settings=Settings(decrease_tolerance=DECISION_TOLERANCE))
    assert lean.converged and "decrease of 2V still to come" in lean.message
    assert lean.iterations < full.iterations and lean.n_simulations < full.n_simulations
    # it stopped at the first iteration whose extrapolated tail is under the tolerance ...
    v = np.array([h["objective"] for h in lean.history])
    decreases = 2.0 * (v[:-1] - v[1:])
    tails = [estimators._remaining_decrease(a, b) for a, b in zip(decreases[:-1], decreases[1:])]
    assert tails[-1] < DECISION_TOLERANCE and all(t >= DECISION_TOLERANCE for t in tails[:-1])
    # ... and the tail was right: the full fit's further decrease of 2V is under the tolerance
    assert 0.0 <= 2.0 * (lean.objective - full.objective) < DECISION_TOLERANCE
    # the iterations both ran are the same iterations
    np.testing.assert_array_equal(v, [h["objective"] for h in full.history[:v.size]])


def test_a_fit_without_combinations_is_the_same_fit_for_fewer_simulations(model, rig_problem):
    start = perturbed_start(model.parameters, 0.3, seed=1)
    reported = estimate(own(rig_problem), start=start, unidentifiable="fix")
    lean = estimate(own(rig_problem), start=start, unidentifiable="fix", settings=Settings(combinations=False))
    assert reported.fixed and len(reported.combinations) == 2 and lean.combinations == []
    np.testing.assert_array_equal(lean.estimate, reported.estimate)
    np.testing.assert_array_equal(lean.std, reported.std)
    assert lean.fixed == reported.fixed
    # the combinations cost one central-difference information matrix of the original free set
    # (the estimate itself the fit has simulated)
    assert reported.n_simulations - lean.n_simulations == 2 * rig_problem.free_index.size


def test_a_singular_start_goes_straight_to_the_fit_that_holds_parameters(model, rig_problem, monkeypatch):
    start = perturbed_start(model.parameters, 0.3, seed=1)
    calls = []
    real = fitting.estimate

    def spy(problem, **kwargs):
        calls.append((kwargs.get("method"), kwargs.get("unidentifiable", "error")))
        return real(problem, **kwargs)

    monkeypatch.setattr(fitting, "estimate", spy)
    fit = fitting._robust_estimate(own(rig_problem), start, Settings())
    assert calls == [("gn", "error"), ("lm", "fix")]
    held = real(own(rig_problem), method="lm", start=start, unidentifiable="fix")
    np.testing.assert_array_equal(fit.estimate, held.estimate)
    assert fit.fixed == held.fixed
    # the Gauss-Newton attempt's start and sensitivities (p + 1 runs, not counted) serve the held
    # fit's first ones
    assert fit.n_simulations == held.n_simulations - (rig_problem.free_index.size + 1)


def test_decision_fits_switch_the_diagnosis_fits_to_both_rules():
    lean = candidates._fit_settings(DiagnosisSettings(decision_fits=True), 8)
    assert lean.decrease_tolerance == DECISION_TOLERANCE and lean.combinations is False
    assert lean.max_iterations == 8
    plain = candidates._fit_settings(DiagnosisSettings(decision_fits=False), 30)
    assert plain.decrease_tolerance is None and plain.combinations is True
    assert plain.tolerance == DiagnosisSettings().tolerance == Settings().tolerance


# --- method version 7: the decrease still to come as the Gauss-Newton step promises it -----------
def test_the_predicted_rule_stops_where_the_full_step_promises_less_than_the_tolerance(model, full_problem):
    start = perturbed_start(model.parameters, 0.3, seed=3, around=model.parameters.nominal)
    full = estimate(full_problem, start=start)
    lean = estimate(full_problem, start=start,
                    settings=Settings(decrease_tolerance=DECISION_TOLERANCE, decrease_estimate="predicted"))
    assert lean.converged and "a full Gauss-Newton step promises" in lean.message
    assert lean.iterations <= full.iterations
    # the iterations both ran are the same iterations, and what was left is within the tolerance
    v = [h["objective"] for h in lean.history]
    np.testing.assert_array_equal(v, [h["objective"] for h in full.history[:len(v)]])
    assert 0.0 <= 2.0 * (lean.objective - full.objective) < DECISION_TOLERANCE


def test_the_predicted_rule_reads_the_model_not_the_history(model, full_problem, monkeypatch):
    """A step that promises much is taken however small the last decreases were (a plateau before a
    large decrease stops the extrapolated rule, not this one); one that promises nothing ends the fit."""
    start = perturbed_start(model.parameters, 0.3, seed=3, around=model.parameters.nominal)
    full = estimate(full_problem, start=start)
    settings = Settings(decrease_tolerance=DECISION_TOLERANCE, decrease_estimate="predicted")
    monkeypatch.setattr(estimators, "_promised_decrease", lambda *args: 1e9)
    never = estimate(full_problem, start=start, settings=settings)
    assert never.iterations == full.iterations and never.objective == full.objective
    monkeypatch.setattr(estimators, "_promised_decrease", lambda *args: 0.0)
    at_once = estimate(full_problem, start=start, settings=settings)
    assert at_once.iterations == 0 and at_once.objective == full.history[0]["objective"]


def test_a_decrease_estimate_and_a_decision_stop_must_be_known():
    with pytest.raises(IdentificationError, match="decrease_estimate 'guessed': choose"):
        Settings(decrease_estimate="guessed")
    with pytest.raises(ValueError, match="decision_stop 'guessed': choose"):
        DiagnosisSettings(decision_stop="guessed")
    lean = candidates._fit_settings(DiagnosisSettings(decision_fits=True, decision_stop="predicted"), 8)
    assert lean.decrease_estimate == "predicted" and lean.decrease_tolerance == DECISION_TOLERANCE
    assert candidates._fit_settings(DiagnosisSettings(**method_switches(6)), 8).decrease_estimate == "extrapolated"
