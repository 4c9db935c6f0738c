"""CLRNet (Zheng et al., CVPR 2022): the cross-layer refinement head (head.py), its learnable line priors
(priors.py), the targets, lane assembly and lane NMS (codec.py), and the assignment and losses (loss.py).
"""

from lanevil_train.models.clrnet.head import CLRNetHead

__all__ = ["CLRNetHead"]
