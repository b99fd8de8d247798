"""The data-driven baseline beside the Cranfield diagnosis: per-cycle features of simulated
records, cross-validation by run, and what it calls a fault kind it was never trained on."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("sklearn")

from ema_uq import get_model, simulate_batch  # noqa: E402
from ema_uq.rigs import cranfield_baseline as baseline  # noqa: E402
from ema_uq.experiments import Experiment, Measurement  # noqa: E402
from ema_uq.models import cranfield  # noqa: E402

MODEL = get_model("cranfield")
CHANNELS = ("position_error", "current")
EFFECT_OF = {"none": None, "play": ("backlash", {"backlash_play": 1e-3}),
             "drag": ("seal_drag", {"seal_drag_dC": 150.0})}


def _profile(cycles: int = 3) -> np.ndarray:
    up = 20.96 + 0.96 * np.arange(125)
    cycle = np.concatenate([up, np.full(75, 140.0), 140.0 - 0.96 * np.arange(1, 125)])
    return np.tile(cycle, cycles) * 1e-3


def _blocks(kind: str, runs=range(1, 5), loads=(20.0, -40.0)) -> list[Measurement]:
    model = MODEL if EFFECT_OF[kind] is None else MODEL.with_effects([EFFECT_OF[kind][0]], EFFECT_OF[kind][1])
    out = []
    for load in loads:
        for run in runs:
            rng = np.random.default_rng([len(kind), int(load) + 100, run])
            set_point = _profile()
            time = np.arange(set_point.size) * 0.04
            inputs = np.column_stack([set_point, np.full(set_point.size, load * cranfield.G0)])
            values = simulate_batch(model, model.parameters.nominal, time, inputs)[:, model.output_index(CHANNELS)]
            values = values + rng.normal(0.0, [1e-4, 0.03], values.shape)
            experiment = Experiment(f"{kind} {load:g} {run}", time, {"x_sp": set_point, "F_load": inputs[:, 1]})
            out.append(Measurement("cranfield", experiment, CHANNELS, values,
                                   {"record_set": kind, "load_kgf": load, "run": run}))
    return out


@pytest.fixture(scope="module")
def table():
    return baseline.CycleTable.of({kind: _blocks(kind) for kind in EFFECT_OF}, {kind: kind for kind in EFFECT_OF})


def test_cycle_features_see_play_in_the_position_error_and_drag_in_the_current(table):
    assert table.x.shape == (3 * 2 * 4 * 3, len(baseline.FEATURES))
    col = {name: i for i, name in enumerate(baseline.FEATURES)}

    def mean(kind, feature):
        return table.x[table.label == kind, col[feature]].mean()

    assert mean("play", "error_start_lag") > mean("none", "error_start_lag") + 3e-4
    assert mean("drag", "current_up_mean") > mean("none", "current_up_mean") + 0.03
    assert abs(mean("drag", "error_start_lag") - mean("none", "error_start_lag")) < 1e-4


def test_cross_validation_by_run_never_trains_on_a_test_run(table):
    cv = baseline.cross_validate(table, n_folds=4)
    assert sorted(r for fold in cv.folds for r in fold) == [1, 2, 3, 4]
    assert all(len(fold) == 1 for fold in cv.folds)
    # simulated kinds well apart: every cycle named right out of fold
    assert cv.accuracy > 0.95 and min(cv.per_class.values()) > 0.9
    assert sum(cv.per_record_set["play"].values()) == int(np.sum(table.label == "play"))


def test_a_kind_left_out_of_training_is_named_as_a_known_one(table):
    named = baseline.leave_one_class_out(table, "play")
    assert set(named) == {"play"}
    assert set(named["play"]) <= {"none", "drag"} and sum(named["play"].values()) == int(np.sum(table.label == "play"))
