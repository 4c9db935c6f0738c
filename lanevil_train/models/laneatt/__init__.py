"""LaneATT (Tabelini et al., CVPR 2021): the head (head.py), its line anchors and target encoding (anchors.py),
and the anchors the train split uses most (frequency.py, anchor_selection=frequency).
"""

from lanevil_train.models.laneatt.head import LaneATTHead

__all__ = ["LaneATTHead"]
