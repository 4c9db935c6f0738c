"""Dataset label formats at the edge of the package: TuSimple JSON lines, CULane .lines.txt.

Readers return plain records (dicts with "image_path" and "lanes", lanes as (N, 2) float
pixel arrays ordered by y descending, in the file's lane order); writers take the same records.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np


def load_image(path: str | Path) -> np.ndarray:
    """Read an image file as an RGB uint8 HxWx3 array; raise naming the path if cv2 cannot."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image not found: {path}")
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ValueError(f"cannot decode image {path} (cv2.imread returned None: corrupt or unsupported)")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


# submodules import nothing from this package module, so importing them last is safe
from lanevil_train.data.formats.culane import read_culane, write_culane, write_culane_lanes  # noqa: E402
from lanevil_train.data.formats.tusimple import read_tusimple, write_tusimple  # noqa: E402

__all__ = ["load_image", "read_tusimple", "write_tusimple", "read_culane", "write_culane", "write_culane_lanes"]
