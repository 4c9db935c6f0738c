"""BezierLaneNet (Feng et al., CVPR 2022): the head (head.py), the Bezier curve fitting and sampling
(bezier.py), and the curve targets, matching and loss (loss.py).
"""

from lanevil_train.models.bezierlanenet.head import BezierLaneNetHead

__all__ = ["BezierLaneNetHead"]
