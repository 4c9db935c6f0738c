"""Lane metrics (TuSimple, CULane; VQA later): plain numpy scores plus torchmetrics wrappers."""

from lanevil_train.metrics.culane import (
    CULaneMetric,
    culane_image_counts,
    culane_summary,
    evaluate_culane_dirs,
)
from lanevil_train.metrics.tusimple import (
    TuSimpleMetric,
    evaluate_tusimple_files,
    tusimple_image_scores,
    tusimple_lane_scores,
    tusimple_summary,
)

__all__ = [
    "CULaneMetric",
    "culane_image_counts",
    "culane_summary",
    "evaluate_culane_dirs",
    "TuSimpleMetric",
    "evaluate_tusimple_files",
    "tusimple_image_scores",
    "tusimple_lane_scores",
    "tusimple_summary",
]
