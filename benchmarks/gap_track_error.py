"""Gap diagnosis on a position sensor whose track carries an error periodic in carriage position.

A mechanism outside the catalogue of either concept: the potentiometer (or linear encoder) of
station 1 reads y1 + a sin(2 pi y1 / pitch), the drive itself unchanged. Written before it ran,
the answers a trustworthy diagnosis gives:

* the verdict is ``unexplained`` (no catalogue mechanism acts on one position channel alone), never a
  named family;
* ``where`` names the channel y1;
* at a pitch equal to the screw lead the error repeats once per screw turn, so the order tracking
  of the localisation (harmonics 1-6 of every shaft) can name it periodic; at a pitch no shaft
  carries it cannot, and the position-periodic structure shows only as the channel and its
  band.

Records: HT/LS, deploy-retract for estimation and the validation run held out, nominal
parameters, 2 % noise, every output channel (``--sensors realistic``: the rig's).

Usage: python benchmarks/gap_track_error.py [--pitches 20,lead] [--amplitude 3] [--seed 11] [--json DIR]
       (--amplitude in noise standard deviations of y1)
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from ema_uq.experiments import Measurement, deploy_retract, noise_std, synthesize, validation
from ema_uq.gap import diagnose
from ema_uq.models import get_model

CONCEPT = "htls"
NOISE = 0.02


def screw_lead(model) -> float:
    """Carriage travel per screw turn [m]: 2 pi r tan(gamma)."""
    c = dict(zip(model.constants.names, model.constants_vector()))
    return 2.0 * math.pi * c["r"] * math.tan(c["gamma"])


def with_track_error(measurement: Measurement, amplitude: float, pitch: float) -> Measurement:
    """The measurement with y1 read through a track error periodic in y1 (``amplitude`` in m)."""
    values = measurement.values.copy()
    j = measurement.channels.index("y1")
    values[:, j] += amplitude * np.sin(2.0 * np.pi * values[:, j] / pitch)
    return Measurement(measurement.concept, measurement.experiment, measurement.channels, values,
                       {**measurement.attrs, "source": "simulated, y1 track error"})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pitches", default="20,lead",
                        help="comma-separated pitches in mm, or 'lead' for the screw lead (default 20,lead)")
    parser.add_argument("--amplitude", type=float, default=3.0, help="error amplitude in noise sd of y1 (default 3)")
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--sensors", choices=("full", "realistic"), default="full")
    parser.add_argument("--json", metavar="DIR", help="also write each diagnosis's GAP.json there")
    args = parser.parse_args()
    model = get_model(CONCEPT)
    lead = screw_lead(model)
    channels = model.sensor_sets[args.sensors]
    records = [synthesize(model, experiment, noise=NOISE, seed=args.seed + k, channels=channels)
               for k, experiment in enumerate((deploy_retract(), validation()))]
    clean_y1 = synthesize(model, deploy_retract(), noise=0.0, channels=("y1",)).values
    amplitude = args.amplitude * float(noise_std(clean_y1, NOISE)[0])
    print(f"{CONCEPT}, {args.sensors} sensors: y1 track error of {amplitude * 1e3:.2f} mm "
          f"({args.amplitude:g} noise sd); screw lead {lead * 1e3:.2f} mm")
    for text in args.pitches.split(","):
        pitch = lead if text.strip() == "lead" else float(text) * 1e-3
        estimation, held = (with_track_error(r, amplitude, pitch) for r in records)
        result = diagnose([estimation], [held], seed=args.seed)
        d = result.to_json()
        if args.json:
            out = Path(args.json) / f"gap_track_{pitch * 1e3:.2f}mm.json"
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_text(json.dumps(d, indent=1, default=float), encoding="utf-8")
        periodic = [r for r in (d.get("localization_held_out") or {}).get("regimes", [])
                    if r.get("name") == "periodic" and r.get("holds_gap")]
        best = d["ranking"][0]["effect"] if d.get("ranking") else "-"
        print(f"  pitch {pitch * 1e3:6.2f} mm ({pitch / lead:.2f} screw turns): {d['verdict']} "
              f"({d.get('confidence')}), best candidate {best}, where {d['where']}, "
              f"periodic named: {periodic[0]['detail'] if periodic else 'no'}, {result.wall_time_s:.0f} s")


if __name__ == "__main__":
    main()
