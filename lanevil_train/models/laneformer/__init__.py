"""LaneFormer (Han et al., AAAI 2022): the DETR-style row-column transformer head (head.py), and the lane
targets, lane assembly, Hungarian assignment and set loss (loss.py).
"""

from lanevil_train.models.laneformer.head import LaneFormerHead

__all__ = ["LaneFormerHead"]
