"""What a decision stop leaves: each fit of a diagnosis that ``decision_fits`` ended early is
continued, and the further decrease of 2V is reported.

Method versions 6 and 7 stop a fit once the decrease of 2V still to come is judged below 0.1
(``DiagnosisSettings.decision_fits``). Version 6 extrapolates that decrease from the last two
decreases; version 7 takes what the full Gauss-Newton step promises. This script tests the
judgement on stored cases. It diagnoses each case with the given version. Whenever a fit ends
by the decision stop, the same fit is continued from its estimate under the paper's rule alone
(relative change of det R below the tolerance), within what is left of its iteration cap. The
decrease of 2V that this continuation finds is what the stop left. The diagnosis itself goes on
with the stopped fit, so its verdict is the version's own. Condition (f) of version 7's
development rule (docs/gap-diagnosis.md) bounds what any stop may leave by 1.

Usage: python benchmarks/gap_fit_trace.py OUTCOME.json [OUTCOME.json ...] --method-version 7
       (OUTCOME.json: a stored case outcome, e.g. benchmarks/protocol_outcomes/.../seed5401/*.json)
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gap import METHOD_VERSIONS, method_settings  # noqa: E402

from ema_uq.gap import fitting  # noqa: E402
from ema_uq.gap.selfcheck import run_case, under_catalogue  # noqa: E402
from ema_uq.gap.selfcheck_scores import CaseOutcome  # noqa: E402

#: condition (f) of method version 7's development rule: the largest decrease of 2V a stop may leave
BOUND = 1.0


def traced_diagnosis(outcome_file: Path, version: int) -> tuple[CaseOutcome, list[dict]]:
    """The case of ``outcome_file`` diagnosed by method ``version``, and one row per fit the
    decision stop ended: its iterations, cap, free parameters and the decrease of 2V it left."""
    settings = method_settings(version)
    case = under_catalogue(CaseOutcome.from_json(json.loads(outcome_file.read_text(encoding="utf-8"))).case,
                           settings)
    original, stops = fitting.estimate, []

    def estimate(problem, method="gn", start=None, settings=None, **kwargs):
        fit = original(problem, method=method, start=start, settings=settings, **kwargs)
        if (settings is not None and settings.decrease_tolerance is not None and fit.converged
                and "decrease of 2V" in fit.message):
            rest = replace(settings, decrease_tolerance=None,
                           max_iterations=max(settings.max_iterations - fit.iterations, 1))
            failed = ""
            try:
                more = original(problem, method=method, start=fit.estimate, settings=rest, **kwargs)
                left = 2.0 * (fit.objective - more.objective)
            except Exception as exc:  # noqa: BLE001 - a continuation that fails leaves nothing measured
                left, failed = float("nan"), f"; continuation failed: {type(exc).__name__}: {exc}"
            stops.append({"fit": len(stops), "method": method, "free": int(problem.free_index.size),
                          "iterations": fit.iterations, "cap": settings.max_iterations, "left": left,
                          "message": fit.message + failed})
        return fit

    fitting.estimate = estimate
    try:
        outcome = run_case(case, settings)
    finally:
        fitting.estimate = original
    return outcome, stops


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("outcomes", nargs="+", type=Path, metavar="OUTCOME.json")
    parser.add_argument("--method-version", type=int, required=True,
                        choices=[v for v in METHOD_VERSIONS if v >= 6])
    args = parser.parse_args()
    worst, unmeasured = 0.0, 0
    for path in args.outcomes:
        if not path.is_file():
            raise SystemExit(f"{path}: no such outcome file; give stored case outcomes (benchmarks/protocol_outcomes)")
        outcome, stops = traced_diagnosis(path, args.method_version)
        print(f"{outcome.case.case_id} (seed {outcome.case.seed}): {outcome.label} ({outcome.confidence}), "
              f"{len(stops)} fit(s) ended by the decision stop")
        for row in stops:
            print(f"    fit {row['fit']:3d} {row['method']} {row['free']:2d} free, {row['iterations']:2d} of "
                  f"{row['cap']:2d} iterations: 2V left {row['left']:10.4g}   ({row['message']})")
        measured = [row["left"] for row in stops if math.isfinite(row["left"])]
        unmeasured += len(stops) - len(measured)
        worst = max([worst, *measured])
    print(f"largest decrease of 2V left by a decision stop: {worst:.4g} (bound of condition (f): {BOUND:g}; "
          f"{'within' if worst <= BOUND else 'EXCEEDED'})"
          + (f"; {unmeasured} stopped fit(s) could not be continued (nan): not measured" if unmeasured else ""))


if __name__ == "__main__":
    main()
