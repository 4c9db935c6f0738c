"""Which QA of a base clip a suite asks: all of them, except in a corruption suite, which draws no illusion and
changes how weather and light look, the questions whose template reads those facts of the scene truth.

Which facts a template reads is found by running it once on a probe truth that logs the keys read (`template_reads`),
so no list of template names has to be kept in step with vlm/clips/qa.py.
"""

from __future__ import annotations

from functools import cache

import numpy as np

from lanevil_train.perturbations import check_kind
from lanevil_train.vlm.clips.qa import KINDS, case_plan, make_qa

# truth keys a corruption-suite question must not read: the illusion is not drawn, weather and light are what the
# weather and brightness corruptions change the look of
CORRUPTION_UNSAFE_FACTS = frozenset(("illusion", "illusion_lane", "weather", "wet", "night"))


def _probe_truth(illusion: str) -> dict:
    """A valid scene truth for probing which facts a QA template reads."""
    return {"curvature_sign": -1, "slope": "flat", "num_lanes": 3, "ego_lane": 1, "weather": "clear_noon",
            "markings": ["yellow_double_solid", "white_dashed", "white_dashed", "white_solid"], "night": False,
            "wet": 0.0, "scene_kind": "urban", "illusion": illusion, "illusion_lane": "left", "ego_speed_mps": 10.0,
            "frame_step_m": 4.0, "segment": "over"}


class _ReadLog(dict):
    """A dict that notes every key read from it."""

    def __init__(self, *args) -> None:
        super().__init__(*args)
        self.read: set = set()

    def __getitem__(self, key):
        self.read.add(key)
        return super().__getitem__(key)

    def get(self, key, default=None):
        self.read.add(key)
        return super().get(key, default)


@cache
def template_reads(category: str, index: int) -> frozenset:
    """The truth keys QA template qa.KINDS[category][index] reads (probed with a traffic and a surface illusion
    and several draws): what decides whether its question holds in a suite that does not draw the illusion."""
    read: set = set()
    for illusion in ("rail_shadow", "vehicle"):
        for draw in range(4):
            truth = _ReadLog(_probe_truth(illusion))
            KINDS[category][index](truth, np.random.default_rng(draw))
            read |= truth.read
    return frozenset(read)


def kept_questions(kind: str, seed: int, segment: str, per_clip: int) -> tuple[int, ...]:
    """Which of make_qa's `per_clip` QA of a base clip a `kind` suite keeps (indices): all of them, or in a
    corruption suite those whose template reads none of CORRUPTION_UNSAFE_FACTS (from qa.case_plan: no truth)."""
    if check_kind(kind) != "corruptions":
        return tuple(range(per_clip))
    plan = case_plan(int(seed), per_clip)[segment]
    return tuple(k for k, (category, index, _) in enumerate(plan)
                 if not template_reads(category, index) & CORRUPTION_UNSAFE_FACTS)


def suite_qa(truth: dict, base: str, seed: int, per_clip: int, kind: str = "illusions") -> list[dict]:
    """The QA of a base clip in a `kind` suite: make_qa's, less those kept_questions leaves out (their qa_ids
    keep their numbers, so a question is the same record in every suite it appears in)."""
    qas = make_qa(truth, base, seed, per_clip)
    return [qas[k] for k in kept_questions(kind, seed, truth["segment"], per_clip)]
