"""SCNN (Pan et al., AAAI 2018): the spatial message passing head (head.py), and the per-slot lane masks,
slot assignment and post-processing (codec.py).
"""

from lanevil_train.models.scnn.head import SCNNHead

__all__ = ["SCNNHead"]
