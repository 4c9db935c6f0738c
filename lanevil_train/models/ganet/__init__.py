"""GANet (Wang et al., CVPR 2022): the keypoint head (head.py), its own neck (neck.py, the official DeformFPN
with the lane-aware feature aggregator), the heatmap targets and keypoint grouping (codec.py), and the losses (loss.py).
"""

from lanevil_train.models.ganet.head import GANetHead

__all__ = ["GANetHead"]
