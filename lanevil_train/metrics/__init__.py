"""Lane metrics (TuSimple, CULane, LLAMAS, CurveLanes; VQA later): plain numpy scores plus torchmetrics wrappers.

Every name loads on first use (module ``__getattr__``), so ``python -m lanevil_train.metrics`` and other
torch-free users import only what they touch: ``tusimple`` needs numpy, ``culane`` numpy and OpenCV, and
only ``wrappers`` (TuSimpleMetric, CULaneMetric) imports torch and torchmetrics. Import the public names
from here: ``from lanevil_train.metrics import TuSimpleMetric, tusimple_lane_scores``.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "CULaneMetric": "wrappers",
    "TuSimpleMetric": "wrappers",
    "culane_image_counts": "culane",
    "culane_image_counts_multi": "culane",
    "culane_leaderboard_scores": "culane",
    "culane_summary": "culane",
    "curvelanes_image_counts": "curvelanes",
    "evaluate_curvelanes_dirs": "curvelanes",
    "culane_sweep_summary": "culane",
    "evaluate_culane_dirs": "culane_files",
    "evaluate_tusimple_files": "tusimple",
    "llamas_image_counts": "llamas",
    "tusimple_count_f1": "tusimple",
    "tusimple_image_scores": "tusimple",
    "tusimple_lane_scores": "tusimple",
    "tusimple_summary": "tusimple",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    """Import the submodule that defines ``name`` on first access (PEP 562) and cache the name here."""
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    """The module's own names plus the lazily exported ones."""
    return sorted(set(globals()) | set(__all__))
