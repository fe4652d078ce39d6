"""Where rays first meet a height field z = h(x, y): a uniform march brackets the crossing, splits narrow it.

One search for both height-field renderers: the seafloor (`synthetic_sequence.render`) and the height-field
patches of the procedural scenes (`procedural_render.render`). Each passes its own sampling and splitting, which
its rendered frames depend on bit for bit.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal

import numpy as np


def first_crossing(gap: Callable[[np.ndarray], np.ndarray], t0: np.ndarray, span: np.ndarray, samples: int,
                   splits: int, method: Literal["bisection", "false_position"],
                   min_drop: float) -> tuple[np.ndarray, np.ndarray]:
    """Ray parameter of each ray's first crossing, and whether the march bracketed one (float32 arrays like t0).

    ``gap(t)`` is the ray's height above the surface at ray parameter ``t`` (an array shaped like ``t0``). It is
    sampled at ``samples`` evenly spaced t over [t0, t0 + span]; the first sample at or below the surface and the
    one before bracket the crossing (found: such a sample exists and is not the first). ``splits`` steps narrow
    the bracket, at its midpoint (``"bisection"``) or where the chord between its end gaps crosses zero
    (``"false_position"``), and the chord of the final bracket gives t. ``min_drop`` floors the gap difference
    the chord divides by. Rays without a bracket get the chord of the first interval.
    """
    fractions = np.linspace(0, 1, samples, dtype=np.float32)
    gaps = np.stack([gap(t0 + span * f) for f in fractions])
    below = gaps <= 0
    first = np.argmax(below, axis=0)
    found = below.any(axis=0) & (first > 0)
    k = np.maximum(first, 1)
    g_lo = np.take_along_axis(gaps, (k - 1)[None], 0)[0]
    g_hi = np.take_along_axis(gaps, k[None], 0)[0]
    hi = t0 + span * fractions[k]
    if method == "bisection":
        lo = t0 + span * fractions[k - 1]
    else:  # one float32 step below the bracketing sample (rounds differently from the previous sample)
        lo = t0 + span * (fractions[k] - fractions[1])
    for _ in range(splits):
        if method == "bisection":
            m = 0.5 * (lo + hi)
        else:
            m = lo + (hi - lo) * g_lo / np.maximum(g_lo - g_hi, min_drop)
        gm = gap(m)
        above = gm > 0
        lo, g_lo = np.where(above, m, lo), np.where(above, gm, g_lo)
        hi, g_hi = np.where(above, hi, m), np.where(above, g_hi, gm)
    drop = np.maximum(g_lo - g_hi, min_drop)
    if method == "bisection":  # the two groupings of the chord round differently; each method keeps its own
        return lo + (hi - lo) * (g_lo / drop), found
    return lo + (hi - lo) * g_lo / drop, found
