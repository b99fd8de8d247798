"""Cranfield rig: the fault diagnosis on real healthy records with a known fault injected.

The seeded-fault record sets of the rig carry one fault each, of a kind the catalogue holds;
what the diagnosis says of a fault outside its catalogue is asked here on the real records
themselves. Each injected set is a copy of the healthy set ``normal`` (all ten runs) whose
measured current is raised while the set point moves, by a known profile; the position error is
left as recorded, so each is a fault seen in the current only. The diagnosis fits the healthy
model on runs 1-5 of ``normal`` as always and judges every set alike, so the injected sets
differ from the healthy fit by the injection and nothing else.

Injected sets (written before the run, with what the right answer is):

* ``spot_*``: a damaged stretch of the screw, a raised-cosine bump of A [A] over centre +- half
  width [mm] of the carriage position, while moving. Outside the catalogue (no candidate
  depends on the position along the stroke): right is ``unexplained`` or ``ambiguous``; a named
  family is wrong. GAP.json's ``where.stroke`` should point at the bump's stroke bin once the
  bump stands above the healthy records' own run-to-run level.
* ``moving_012``: 0.12 A more whenever the set point moves, the size of the lubrication sets'
  current change under positive loads. A friction increase as the current sees it, without the
  position loop's answer to it: ``lubrication_loss`` or ``contact_friction`` would be a fair
  name, ``unexplained`` an honest one (the position error did not change with it).

Usage: python benchmarks/cranfield_injected.py
Needs the record sets ($EMA_UQ_CRANFIELD_DIR or ../shared/data/real/cranfield_linear_actuator).
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

from ema_uq import io
from ema_uq.rigs import cranfield as study

#: name -> (amplitude [A], centre [mm], half width [mm]); centre None: everywhere while moving
INJECTED = {
    "spot_010_80mm": (0.10, 80.0, 10.0),
    "spot_020_80mm": (0.20, 80.0, 10.0),
    "spot_040_80mm": (0.40, 80.0, 10.0),
    "spot_030_40mm": (0.30, 40.0, 20.0),
    "spot_015_110mm": (0.15, 110.0, 8.0),
    "moving_012": (0.12, None, None),
}


def inject(healthy: pd.DataFrame, amplitude: float, centre: float | None, half: float | None) -> pd.DataFrame:
    """A copy of ``healthy`` whose current is raised by the profile while the set point moves."""
    position = (healthy.set_point - healthy.position_error).to_numpy()
    moving = np.abs(np.gradient(healthy.set_point.to_numpy())) > 1e-6
    if centre is None:
        window = np.ones_like(position)
    else:
        xi = (position - centre) / half
        window = np.where(np.abs(xi) < 1.0, 0.5 * (1.0 + np.cos(np.pi * xi)), 0.0)
    out = healthy.copy()
    out["current"] = healthy.current + amplitude * window * moving
    out["fault_type"] = -1
    return out


def main() -> None:
    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args()
    healthy = pd.read_csv(io.cranfield_file("normal"))
    with tempfile.TemporaryDirectory() as folder:
        healthy.to_csv(Path(folder) / "normal.csv", index=False)
        for name, profile in INJECTED.items():
            inject(healthy, *profile).to_csv(Path(folder) / f"{name}.csv", index=False)
        os.environ[io.CRANFIELD_DIR_ENV] = folder
        t0 = time.perf_counter()
        records = io.CranfieldRecords(channels=study.CHANNELS)
        result = study.run_study(records.read, record_sets=("normal", *INJECTED), runs_of=records.runs_of)
    print(f"[[Injected faults on the healthy records]] {len(INJECTED)} sets, {time.perf_counter() - t0:.0f} s")
    print(f"    {'set':<16} {'injected':<26} {'verdict':<12} {'family':<18} {'best partial':<18} {'closes':>7}  "
          f"{'where along the stroke':<34} structure left by the best partial")
    for name, diagnosis in zip(("normal", *INJECTED), result.diagnoses):
        row, r = diagnosis.row(), diagnosis.result
        amplitude, centre, half = INJECTED.get(name, (0.0, None, None))
        injected = ("-" if name == "normal" else f"+{amplitude:.2f} A moving"
                    + ("" if centre is None else f", {centre:.0f}+-{half:.0f} mm"))
        closes = row.get("reproducible_shrink")
        left = "; ".join(f"{group}: {cells[0].split(' (')[0]}" for group, cells in
                         (r.open_set.get("where_left") or {}).items())
        stroke = "; ".join(text.split(", holds")[0] + ")" for text in r.where.get("stroke", [])) or "-"
        print(f"    {name:<16} {injected:<26} {r.verdict:<12} {r.family or '-':<18} {row['best'] or '-':<18} "
              f"{'-' if closes is None or not np.isfinite(closes) else f'{closes:.2f}':>7}  {stroke:<34} {left or '-'}")


if __name__ == "__main__":
    main()
