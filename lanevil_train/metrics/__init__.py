"""Lane metrics (TuSimple now; CULane and VQA later): plain numpy scores plus torchmetrics wrappers."""

from lanevil_train.metrics.tusimple import (
    TuSimpleMetric,
    evaluate_tusimple_files,
    tusimple_image_scores,
    tusimple_summary,
)

__all__ = ["TuSimpleMetric", "evaluate_tusimple_files", "tusimple_image_scores", "tusimple_summary"]
