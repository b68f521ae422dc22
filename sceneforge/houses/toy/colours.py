"""The toy houses' colours: a base colour per label family, jittered into a colour of each
instance's own (the generator's rule, which the hard cases follow for the instances they add)."""

from __future__ import annotations

import numpy as np

#: a base colour per label family; each instance jitters it into a colour of its own
PALETTE = {
    "wall": (0.85, 0.83, 0.78), "floor": (0.55, 0.40, 0.28), "ceiling": (0.93, 0.93, 0.91),
    "door": (0.60, 0.45, 0.30), "window": (0.90, 0.90, 0.92), "curtain": (0.70, 0.25, 0.28),
    "blinds": (0.85, 0.85, 0.78), "picture": (0.30, 0.50, 0.70), "floor_mat": (0.60, 0.30, 0.30),
    "mirror": (0.80, 0.86, 0.90), "bed": (0.45, 0.35, 0.60), "pillow": (0.92, 0.88, 0.82),
    "night_stand": (0.50, 0.35, 0.20), "lamp": (0.92, 0.84, 0.50), "dresser": (0.55, 0.40, 0.25),
    "box": (0.70, 0.60, 0.40), "bookshelf": (0.45, 0.30, 0.20), "books": (0.25, 0.40, 0.60),
    "sofa": (0.30, 0.45, 0.35), "table": (0.60, 0.45, 0.30), "otherprop": (0.85, 0.85, 0.85),
    "cabinet": (0.65, 0.55, 0.45), "television": (0.12, 0.12, 0.14), "counter": (0.75, 0.75, 0.72),
    "refridgerator": (0.90, 0.90, 0.92), "chair": (0.50, 0.30, 0.20), "bathtub": (0.95, 0.95, 0.95),
    "toilet": (0.94, 0.94, 0.94), "sink": (0.92, 0.92, 0.94), "desk": (0.55, 0.45, 0.35),
    "shelves": (0.50, 0.40, 0.30),
}


def instance_colour(rng, category: str, used: set) -> tuple[float, float, float, float]:
    """The category's base colour, jittered until no other instance of the house has it."""
    base = np.array(PALETTE[category])
    while True:
        rgb = tuple(round(float(c), 3) for c in np.clip(base + rng.uniform(-0.1, 0.1, 3), 0.02, 0.98))
        if rgb not in used:
            used.add(rgb)
            return (*rgb, 1.0)
