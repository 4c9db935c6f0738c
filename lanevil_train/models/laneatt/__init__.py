"""LaneATT (Tabelini et al., CVPR 2021): the head (head.py), its line anchors and target encoding (anchors.py),
and the choice of the anchors the train split uses most from their counts (frequency.py,
anchor_selection=frequency; the counting: tasks/detector/anchor_use.py).
"""

from lanevil_train.models.laneatt.head import LaneATTHead

__all__ = ["LaneATTHead"]
