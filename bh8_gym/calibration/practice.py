"""Practice hands: the simulator with parameters drawn away from the defaults, standing in for a
real hand whose constants nobody knows (`bh8 calibrate draw`, the tests, the benchmark). Served by
`bh8 serve --hand-parameters hidden.toml`, recorded and fitted like a real one, they tell whether
the calibration finds what was hidden."""
from __future__ import annotations

import numpy as np

from bh8_gym.calibration.fit import CHECKED, FIT_PARAMETERS, TIED
from bh8_gym.plant.parameters import PlantParameters

DRAW_SPREAD = 0.30  # each parameter within ±30 % of its default (wider than the randomisation's ranges)
# Beyond the fitted parameters, what a real hand also differs in (`draw_hand(..., everything=True)`):
# the parameters the fit holds (TIED) or finds untold (CHECKED) and the gauges' offsets.
FITTED = tuple(p.name for p in FIT_PARAMETERS)
UNFITTED = tuple(TIED) + tuple(p.name for p in CHECKED)


def draw_hand(rng: np.random.Generator, spread: float = DRAW_SPREAD, everything: bool = False) -> dict:
    """PlantParameters fields of a practice hand: each fitted parameter (and with `everything` the
    others a hand differs in) its default times a factor uniform in 1 ± `spread`, the gauges'
    offsets uniform in 100..140 (SPEC.md §1), and the gauges' gain like the fitted parameters."""
    if not 0.0 <= spread < 1.0:
        raise ValueError(f"spread must be in [0, 1), got {spread!r}")
    defaults = PlantParameters()
    names = FITTED + (UNFITTED if everything else ())
    values = {name: float(getattr(defaults, name)) * float(rng.uniform(1.0 - spread, 1.0 + spread)) for name in names}
    values["strain_offsets"] = tuple(int(v) for v in rng.integers(100, 141, size=3))
    # drawn last, so a seed's other values are those it drew before the gain was drawn too
    values["strain_gain"] = float(defaults.strain_gain) * float(rng.uniform(1.0 - spread, 1.0 + spread))
    return values
