"""The RK4 kernel compiled for one effect set: the generic kernel's numbers, and the rule that
decides when a set gets one (ema_uq.simulate.specialise)."""
from __future__ import annotations

import numpy as np
import pytest

from ema_uq import deploy_retract, get_model
from ema_uq.simulate import specialise
from ema_uq.simulate.dispatch import kernel_key
from ema_uq.simulate.integrators import _integrate_batch_flags


def _kernel_arguments(model, n_sets: int, seed: int):
    """Arguments of the RK4 effects entry for ``n_sets`` parameter sets spread around nominal on
    the first 6 s of deploy-retract (both directions of motion, the load reversal)."""
    experiment = deploy_retract().slice(0, 600)
    rng = np.random.default_rng(seed)
    nominal = model.parameters.nominal
    thetas = np.ascontiguousarray(nominal * rng.uniform(0.8, 1.2, size=(n_sets, nominal.size)))
    n_sub = max(1, int(np.ceil(experiment.dt / model.rk4_step - 1e-9)))
    out = np.empty((n_sets, experiment.n_samples, model.n_outputs))
    rest = (model.kernel_constants(), np.ascontiguousarray(experiment.input_matrix(model)),
            np.zeros(model.n_states), experiment.dt / n_sub, n_sub, out)
    return thetas, rest


@pytest.mark.parametrize("concept, effects", [("htls", ["stribeck", "load_dependent_friction"]),
                                              ("lths", ["shaft_compliance"])])
def test_the_specialised_kernel_computes_the_generic_kernels_numbers_bit_for_bit(concept, effects):
    model = get_model(concept).with_effects(effects)
    model_id, flags = kernel_key(model)
    assert flags != 0
    thetas, rest = _kernel_arguments(model, 3, seed=5)
    generic_out, specialised_out = rest[-1], np.empty_like(rest[-1])
    _integrate_batch_flags(model_id, flags, thetas, *rest)
    entry = specialise.specialise(model_id, flags, thetas, *rest[:-1], specialised_out)
    entry(model_id, flags, thetas, *rest[:-1], specialised_out)
    assert np.all(np.isfinite(generic_out))
    assert np.array_equal(generic_out, specialised_out)


@pytest.fixture
def fresh_policy(monkeypatch):
    """The rule's state emptied, the kernels replaced by records of what ran and was compiled."""
    log = {"compiled": [], "ran": []}
    monkeypatch.setattr(specialise, "_ENTRIES", {})
    monkeypatch.setattr(specialise, "_PROBED", set())
    monkeypatch.setattr(specialise, "_GENERIC_SECONDS", specialise.defaultdict(float))
    monkeypatch.setattr(specialise, "SPECIALISE_AFTER_S", 1.0)
    clock = iter(range(0, 1000, 1))          # each generic run lasts 0.5 s of this clock
    monkeypatch.setattr(specialise.time, "perf_counter", lambda: next(clock) * 0.5)
    monkeypatch.setattr(specialise, "_integrate_batch_flags", lambda *args: log["ran"].append("generic"))

    def fake_compile(key, signature):
        log["compiled"].append(key)
        specialise._ENTRIES[key] = lambda *args: log["ran"].append("specialised")
        return specialise._ENTRIES[key]

    monkeypatch.setattr(specialise, "_compile", fake_compile)
    return log


def test_an_effect_set_is_specialised_once_its_generic_runs_took_long_enough(fresh_policy, monkeypatch):
    monkeypatch.setattr(specialise, "_cached", lambda signature: False)
    for _ in range(4):
        specialise.run_rk4_effects(0, 2, np.zeros((4, 3)), np.zeros(2))
    # 0.5 s, 1.0 s of generic runs, then the set's own kernel
    assert fresh_policy["ran"] == ["generic", "generic", "specialised", "specialised"]
    assert fresh_policy["compiled"] == [(0, 2)]
    specialise.run_rk4_effects(1, 2, np.zeros((4, 3)), np.zeros(2))      # another set counts on its own
    assert fresh_policy["ran"][-1] == "generic"


def test_an_effect_set_whose_kernel_is_in_the_cache_runs_specialised_at_once(fresh_policy, monkeypatch):
    looked = []
    monkeypatch.setattr(specialise, "_cached", lambda signature: looked.append(signature) or True)
    specialise.run_rk4_effects(0, 4, np.zeros((1, 3)), np.zeros(2))
    assert fresh_policy["ran"] == ["specialised"] and fresh_policy["compiled"] == [(0, 4)]
    assert looked[0][0].literal_value == 0 and looked[0][1].literal_value == 4


def test_the_cache_is_looked_in_once_per_effect_set(fresh_policy, monkeypatch):
    looked = []
    monkeypatch.setattr(specialise, "_cached", lambda signature: looked.append(signature) or False)
    monkeypatch.setattr(specialise, "SPECIALISE_AFTER_S", 100.0)
    for _ in range(3):
        specialise.run_rk4_effects(0, 8, np.zeros((1, 3)), np.zeros(2))
    assert len(looked) == 1 and fresh_policy["compiled"] == [] and fresh_policy["ran"] == ["generic"] * 3
