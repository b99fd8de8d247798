"""The rig descriptor and the figures picked by concept: a report module draws arrays, a
diagnosis strategy carries no figure, concept names are asked of the rig."""
from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np

from ema_uq.gap.strategy import DiagnosisStrategy
from ema_uq.report import gap_figures
from ema_uq.rigs import RIGS, is_measured, rig_of


def test_rigs_answer_for_their_concepts():
    assert rig_of("htls") is None and rig_of("lths") is None and not is_measured("htls")
    for concept in RIGS:
        rig = rig_of(concept)
        assert rig.concept == concept and is_measured(concept)
        assert all(len(row) == 2 for row in rig.data_files({}))
    assert rig_of("cranfield").fault_diagnosis and not rig_of("emps").fault_diagnosis
    assert rig_of("emps").gap_figure_data is not None and rig_of("emps").record_constants is not None


def test_old_emps_module_name_is_the_rig_module():
    import ema_uq.emps_benchmark as old
    import ema_uq.rigs.emps as new

    assert old is new and old.EMPS_STRATEGY is new.EMPS_STRATEGY


def test_a_strategy_carries_no_figure():
    assert "figure" not in {f.name for f in dataclasses.fields(DiagnosisStrategy)}


def test_the_emps_gap_figure_draws_arrays_only(monkeypatch):
    t = np.linspace(0.0, 1.0, 200)
    data = {"time": t, "before": np.sin(20 * t), "after": 0.5 * np.sin(20 * t), "after_label": "+ delay",
            "reference": t ** 2, "regimes": {"low_speed": t < 0.3, "constant_speed": t >= 0.3}}
    fig = gap_figures.gap_figure("emps", result=None, data=data)
    assert len(fig.axes) == 3   # residual, its reference twin, RMS by regime
    # no arrays (or a concept without a figure of its own): the ledger of the result
    drawn = []
    monkeypatch.setattr(gap_figures, "gap_ledger", lambda result: drawn.append(result) or "ledger")
    ledger_of = SimpleNamespace()
    assert gap_figures.gap_figure("emps", ledger_of, None) == "ledger"
    assert gap_figures.gap_figure("htls", ledger_of, data) == "ledger" and drawn == [ledger_of, ledger_of]
