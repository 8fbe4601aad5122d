"""Is this input inside what the model was trained on? Checked against the spec in the checkpoint.

A GNS interpolates: a frame rate, a gravity, a shape or a speed it never saw in training gives
predictions nobody measured. Rollouts still run, but each such input gets one warning line
naming the quantity, the value seen and the trained range, so a user knows what to trust.
"""
from __future__ import annotations

import numpy as np

from gns.spec import ModelSpec

# A value may exceed the trained range by this fraction of the range's magnitude before a
# warning: test data drawn from the training distribution rarely matches its extremes exactly.
SLACK = 0.1

UNITS = {"speed": "units/s", "angular_speed": "rad/s", "height": "units", "scale": "", "friction": "",
         "restitution": ""}


def outside_training(trained: ModelSpec, data: ModelSpec) -> list[str]:
    """Warnings (one line each) for `data` (a gns.data.feature_spec of the input scenes)
    falling outside `trained` (the checkpoint's spec)."""
    out = []
    if not np.isclose(trained.frame_rate, data.frame_rate, rtol=1e-6):
        out.append(f"frame rate {data.frame_rate:g} fps, the model was trained at {trained.frame_rate:g} fps "
                   "(it predicts one frame ahead: resample the data)")
    if not np.allclose(trained.gravity, data.gravity, rtol=1e-6):
        out.append(f"gravity {list(data.gravity)}, trained with {list(trained.gravity)}")
    if (trained.floor is None) != (data.floor is None):
        out.append("the model was trained " + ("without" if trained.floor is None else "with") + " a floor")
    unseen = sorted(set(data.shapes) - set(trained.shapes))
    if unseen:
        out.append(f"shape(s) {', '.join(unseen)} not seen in training ({', '.join(trained.shapes)})")
    for key, (lo, hi) in trained.ranges.items():
        if key not in data.ranges:
            continue
        dlo, dhi = data.ranges[key]
        slack = SLACK * max(abs(lo), abs(hi), 1e-9)
        if dlo < lo - slack or dhi > hi + slack:
            unit = f" {UNITS.get(key, '')}".rstrip()
            out.append(f"{key.replace('_', ' ')} {dlo:.3g} to {dhi:.3g}{unit} is outside the trained "
                       f"{lo:.3g} to {hi:.3g}{unit}")
    return out
