"""A data-driven baseline beside the Cranfield fault diagnosis: a classifier of per-cycle
features, trained on labelled fault records.

What each needs and where each wins:

- The *diagnosis* (:mod:`ema_uq.rigs.cranfield`) needs healthy records only: it fits the rig model
  on them and asks which effect of a physical catalogue explains a new record set's gap, or
  says ``unexplained`` when none does. It can name a fault kind it has never seen recorded,
  and it can refuse one outside its catalogue.
- The *baseline* needs labelled records of every fault kind it is to name, under the loads
  and set points it will meet; given those it may separate the kinds it was trained on better
  than a physical model, since it uses whatever differs between the records, physical or not
  (a different test session's drift included). It cannot say "none of mine": a record of a
  kind it never saw is put in one of the classes it knows (:func:`leave_one_class_out` shows
  which).

Features (:func:`cycle_features`): per set-point cycle of a record (the records repeat one
trapezoid), from the set point and the two measured channels: the mean, standard deviation and
RMS of the drive current on the moving up stroke, the moving down stroke and the top dwell; the
mean and standard deviation of the position error on each stroke; the largest lag at the
start of the up stroke (after the reversal at the bottom, where play shows), the overshoot at
the stop at the top; and the load. "Moving" leaves out ``START_S`` after every change of the
set-point speed, as the diagnosis's regimes do.

Classifier: a random forest (scikit-learn, seeded; no feature scaling needed, no tuning: the
library's defaults but the tree count). Cross-validation by run: every record set holds runs
1-10 per load, recorded in order, and runs of one number are grouped (GroupKFold), so a test
run is never in training, in any record set; otherwise neighbouring cycles of one run, nearly
identical, would sit on both sides and the accuracy would be that of recognising a run.

Pure numerics on :class:`~ema_uq.experiments.Measurement` blocks (read by
:func:`ema_uq.io.read_cranfield`); needs scikit-learn (the ``baseline`` extra).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from .cranfield import START_S
from .cranfield_cycles import set_point_period
from ..experiments import Measurement

FEATURES = ("load_kgf",
            "current_up_mean", "current_up_std", "current_up_rms",
            "current_down_mean", "current_down_std", "current_down_rms",
            "current_dwell_mean", "current_dwell_std",
            "error_up_mean", "error_up_std", "error_down_mean", "error_down_std",
            "error_start_lag", "error_stop_overshoot")
#: folds of the cross-validation by run (10 runs: two run numbers per fold)
N_FOLDS = 5


def _cycle_regions(x_sp: np.ndarray, dt: float) -> dict[str, np.ndarray]:
    """Masks of one cycle: moving up, moving down (each after ``START_S``), the top dwell
    after it, the start window of the up stroke and the window after its stop."""
    direction = np.sign(np.round(np.append(np.diff(x_sp), 0.0) / dt, 9))
    reach = int(round(START_S / dt))
    changes = np.concatenate([[0], np.flatnonzero(np.diff(direction) != 0) + 1])
    near = np.zeros(x_sp.size, dtype=bool)
    for k in changes:
        near[k: k + reach] = True
    up_start = np.zeros(x_sp.size, dtype=bool)
    stop = np.zeros(x_sp.size, dtype=bool)
    for k in changes:
        if direction[k] > 0:
            up_start[k: k + reach] = True
        elif direction[k] == 0 and k > 0 and direction[k - 1] > 0:
            stop[k: k + reach] = True
    return {"up": (direction > 0) & ~near, "down": (direction < 0) & ~near, "dwell": (direction == 0) & ~near,
            "up_start": up_start, "stop": stop}


def cycle_features(measurement: Measurement) -> np.ndarray:
    """(cycles, len(FEATURES)) features of every whole set-point cycle of one block (none when
    the set point does not repeat). Needs the channels ``position_error`` and ``current``."""
    x_sp = measurement["x_sp"]
    period = set_point_period(x_sp)
    if period is None:
        return np.zeros((0, len(FEATURES)))
    current, error = measurement["current"], measurement["position_error"]
    regions = _cycle_regions(x_sp[:period], measurement.experiment.dt)
    load = float(measurement["F_load"][0]) / 9.80665
    rows = []
    for start in range(0, x_sp.size - period + 1, period):
        i, e = current[start: start + period], error[start: start + period]
        row = [load]
        for part in ("up", "down"):
            v = i[regions[part]]
            row += [v.mean(), v.std(), np.sqrt(np.mean(v ** 2))]
        v = i[regions["dwell"]]
        row += [v.mean(), v.std()]
        for part in ("up", "down"):
            v = e[regions[part]]
            row += [v.mean(), v.std()]
        row += [e[regions["up_start"]].max() if regions["up_start"].any() else 0.0,
                -e[regions["stop"]].min() if regions["stop"].any() else 0.0]
        rows.append(row)
    return np.array(rows)


@dataclass
class CycleTable:
    """Features ``x`` (n, len(FEATURES)) of every cycle, its ``label``, ``record_set`` and ``run``."""

    x: np.ndarray
    label: np.ndarray
    record_set: np.ndarray
    run: np.ndarray

    @classmethod
    def of(cls, blocks: Mapping[str, Sequence[Measurement]], labels: Mapping[str, str]) -> "CycleTable":
        """From the blocks of each record set and the label of each set (e.g. the fault kind)."""
        xs, label, sets, runs = [], [], [], []
        for name, ms in blocks.items():
            for m in ms:
                f = cycle_features(m)
                xs.append(f)
                label += [labels[name]] * len(f)
                sets += [name] * len(f)
                runs += [int(m.attrs["run"])] * len(f)
        return cls(np.concatenate(xs), np.array(label), np.array(sets), np.array(runs))

    def subset(self, keep: np.ndarray) -> "CycleTable":
        return CycleTable(self.x[keep], self.label[keep], self.record_set[keep], self.run[keep])


def classifier(seed: int = 0):
    """The baseline's classifier: a seeded random forest of 300 trees."""
    from sklearn.ensemble import RandomForestClassifier

    return RandomForestClassifier(n_estimators=300, random_state=seed, n_jobs=1)


@dataclass
class CrossValidation:
    """Out-of-fold predictions of the cross-validation by run: ``predicted`` per cycle of
    ``table``, ``accuracy`` overall, ``per_class`` recall (share of a class's cycles named
    right), ``per_record_set`` the counts of each predicted label and ``folds`` the run numbers
    held out in each fold."""

    table: CycleTable
    predicted: np.ndarray
    accuracy: float
    per_class: dict[str, float]
    per_record_set: dict[str, dict[str, int]]
    folds: list[list[int]] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return {"accuracy": self.accuracy, "per_class": self.per_class, "per_record_set": self.per_record_set,
                "folds": self.folds, "n_cycles": int(self.table.label.size), "features": list(FEATURES)}


def _counts(values: np.ndarray) -> dict[str, int]:
    names, counts = np.unique(values, return_counts=True)
    return {str(n): int(c) for n, c in zip(names, counts)}


def cross_validate(table: CycleTable, *, n_folds: int = N_FOLDS, seed: int = 0) -> CrossValidation:
    """Cross-validation grouped by run number (GroupKFold): the cycles of a test run, in every
    record set, are never in training."""
    from sklearn.model_selection import GroupKFold

    predicted = np.empty(table.label.size, dtype=table.label.dtype)
    folds = []
    for train, test in GroupKFold(n_splits=n_folds).split(table.x, table.label, groups=table.run):
        assert not set(table.run[train]) & set(table.run[test])
        model = classifier(seed).fit(table.x[train], table.label[train])
        predicted[test] = model.predict(table.x[test])
        folds.append(sorted(int(r) for r in set(table.run[test])))
    right = predicted == table.label
    per_class = {str(c): float(right[table.label == c].mean()) for c in np.unique(table.label)}
    per_set = {str(s): _counts(predicted[table.record_set == s]) for s in dict.fromkeys(table.record_set)}
    return CrossValidation(table, predicted, float(right.mean()), per_class, per_set, folds)


def leave_one_class_out(table: CycleTable, left_out: str, *, seed: int = 0) -> dict[str, dict[str, int]]:
    """Train on every cycle of the other classes and name the cycles of class ``left_out``:
    per record set of that class the counts of each label it is given. A classifier has no
    label for a kind it never saw, so every count falls on a trained class."""
    train = table.label != left_out
    model = classifier(seed).fit(table.x[train], table.label[train])
    test = table.subset(~train)
    predicted = model.predict(test.x)
    return {str(s): _counts(predicted[test.record_set == s]) for s in dict.fromkeys(test.record_set)}
