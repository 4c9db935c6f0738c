"""A stand-in for vlm/clips/clips.py (the renderer) with its API: tiny deterministic frames and a fixed truth."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from tests.vlm.truth_fixture import truth

CALLS = {"render": 0}


@dataclass(frozen=True)
class ClipCase:
    case_id: str
    seed: int
    illusion: str


def clip_cases(num_cases: int, first_seed: int, illusions: Sequence[str]) -> list[ClipCase]:
    return [ClipCase(f"case-{first_seed + i:07d}", first_seed + i, illusions[i % len(illusions)])
            for i in range(num_cases)]


def render_clip(case, segment, severities, size=(360, 640)) -> dict[int, list[np.ndarray]]:
    CALLS["render"] += 1
    rng = np.random.default_rng([case.seed, ("before", "over", "alongside").index(segment)])
    clean = [rng.integers(0, 256, (*size, 3), dtype=np.uint8) for _ in range(6)]
    out = {0: clean} if 0 in severities else {}
    for s in (s for s in severities if s):
        frames = [f.copy() for f in clean]
        for f in frames:
            f[: 2 * s, : 3 * s] = 0  # the "illusion": a dark patch growing with severity
        out[s] = frames
    return out


def clip_truth(case, segment, size=(360, 640)) -> dict:
    return truth(segment=segment, illusion=case.illusion, num_lanes=2 + case.seed % 4, ego_lane=0,
                 markings=["yellow_solid"] + ["white_dashed"] * (1 + case.seed % 4) + ["white_solid"])
