"""Small statistics shared by the closed loop's tables and the robustness card (no heavy imports)."""

from __future__ import annotations

import math

Z95 = 1.959963984540054  # the standard normal's 97.5 % quantile: a two-sided 95 % interval


def wilson_interval(successes: int, runs: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval of a success proportion (in [0, 1]); (0, 1) for no runs."""
    if runs <= 0:
        return 0.0, 1.0
    p = successes / runs
    centre = (p + z * z / (2 * runs)) / (1 + z * z / runs)
    half = z * math.sqrt(p * (1 - p) / runs + z * z / (4 * runs * runs)) / (1 + z * z / runs)
    return max(0.0, centre - half), min(1.0, centre + half)
