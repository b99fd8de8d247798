"""Cranfield rig: does the position-error change of the faulted record sets follow the friction?

The diagnosis leaves the lubrication sets ``unexplained``: ``lubrication_loss`` wins the evidence
margin on the current but leaves structure in the position error (the 2-10 % band of Nyquist,
the loop's recovery after each corner of the cycle), and no friction candidate moves the
model's position loop. This script measures, from the records alone (no model), whether that
position-error change could be the friction's at all: per record set and load it compares
with the healthy set, run means over the ten runs (cycles 2-5 of each run averaged),

* the moving current of the up and down strokes (the friction a drive delivers; samples
  1.2-4.8 s of each stroke),
* the position error 0.5-1.0 s after a stroke starts (the start lag's recovery) and
  0.4-1.0 s after the top stop (the overshoot's creep back),

each change with its Welch t over runs, then the correlation over the (set, load) cells of the
lubrication sets between the creep-back change and the current change, and the same position
figures between the healthy set's own loads (its test sessions), for scale.

Usage: python benchmarks/cranfield_position_error.py
Needs the record sets ($EMA_UQ_CRANFIELD_DIR or ../shared/data/real/cranfield_linear_actuator).
"""
from __future__ import annotations

import argparse

import numpy as np

from ema_uq import io

CYCLE = 324                       # samples per motion cycle (12.96 s at 25 Hz)
UP_CURRENT, DOWN_CURRENT = slice(30, 120), slice(230, 320)
START_RECOVERY = slice(12, 26)    # 0.5-1.0 s after the up stroke starts
CREEP_BACK = slice(135, 150)      # 0.4-1.0 s after the top stop (sample 125)
LOADS = (20.0, 40.0, -40.0)
SETS = ("normal", "lackLubrication1", "lackLubrication2", "backlash1", "backlash2")


def run_figures(name: str) -> dict[float, dict[str, np.ndarray]]:
    """Per load, per figure: one value per run (cycles 2-5 averaged; the first cycle starts at rest)."""
    out: dict[float, dict[str, list[float]]] = {}
    for block in io.read_cranfield(io.cranfield_file(name), channels=("position_error", "current")):
        cycles = block.values.reshape(-1, CYCLE, 2)[1:].mean(axis=0)
        error_mm, current = cycles[:, 0] * 1e3, cycles[:, 1]
        figures = out.setdefault(block.attrs["load_kgf"], {k: [] for k in ("I_up", "I_dn", "start", "creep")})
        figures["I_up"].append(current[UP_CURRENT].mean())
        figures["I_dn"].append(current[DOWN_CURRENT].mean())
        figures["start"].append(error_mm[START_RECOVERY].mean())
        figures["creep"].append(error_mm[CREEP_BACK].mean())
    return {load: {k: np.array(v) for k, v in f.items()} for load, f in out.items()}


def change(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Mean of a less mean of b and its Welch t."""
    d = a.mean() - b.mean()
    return float(d), float(d / np.sqrt(a.var(ddof=1) / a.size + b.var(ddof=1) / b.size))


def main() -> None:
    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args()
    figures = {name: run_figures(name) for name in SETS}
    healthy = figures["normal"]
    print("[[Change against the healthy set, same load]] mean over runs (Welch t)")
    print(f"    {'record set':<18}{'load':>6}  {'moving current up/down [A]':>30}  {'start recovery [mm]':>20}"
          f"  {'creep back [mm]':>16}")
    cells = []
    for name in SETS[1:]:
        for load in LOADS:
            f, h = figures[name][load], healthy[load]
            up, dn = change(f["I_up"], h["I_up"]), change(f["I_dn"], h["I_dn"])
            start, creep = change(f["start"], h["start"]), change(f["creep"], h["creep"])
            cells.append((name, load, up[0] + dn[0], creep[0]))
            print(f"    {name:<18}{load:>6g}  {up[0]:+8.3f} ({up[1]:+5.1f}) / {dn[0]:+7.3f} ({dn[1]:+5.1f})"
                  f"  {start[0]:+8.3f} ({start[1]:+5.1f})  {creep[0]:+7.3f} ({creep[1]:+5.1f})")
    lubrication = np.array([(c[2], c[3]) for c in cells if c[0].startswith("lackLubrication")])
    r = np.corrcoef(lubrication[:, 0], lubrication[:, 1])[0, 1]
    print(f"[[Does the position error follow the friction?]] lubrication sets, {len(lubrication)} (set, load) cells:"
          f" correlation of the creep-back change with the moving-current change r = {r:+.2f}")
    print("[[The healthy set's own loads]] (each load recorded as a series of tests of its own)")
    for a, b in ((40.0, -40.0), (40.0, 20.0), (20.0, -40.0)):
        start, creep = change(healthy[a]["start"], healthy[b]["start"]), change(healthy[a]["creep"], healthy[b]["creep"])
        print(f"    normal {a:+g} kgf vs {b:+g} kgf: start recovery {start[0]:+.3f} mm ({start[1]:+.1f}), "
              f"creep back {creep[0]:+.3f} mm ({creep[1]:+.1f})")


if __name__ == "__main__":
    main()
