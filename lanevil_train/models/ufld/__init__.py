"""UFLD (Qin et al., ECCV 2020): the row-wise classification head (head.py), the row anchors, cells and
lane slots (codec.py), and the structural and auxiliary segmentation losses (losses.py).
"""

from lanevil_train.models.ufld.head import UFLDHead

__all__ = ["UFLDHead"]
