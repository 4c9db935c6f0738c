"""Image files of a dataset: a cheap check when labels are read, and the full decode when a sample is loaded."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np


def image_file_problem(path: str | Path) -> str | None:
    """Why `path` cannot be an image (missing, empty, not an image format cv2 reads), or None if it looks fine.

    Reads only the file's first bytes (its signature), a few microseconds an image, so label readers check
    every image before any long work starts. A file cut short after a valid header passes; `load_image` finds it.
    """
    path = Path(path)
    if path.is_dir():
        return "is a directory, not an image file"
    if not path.is_file():
        return "not found"
    if path.stat().st_size == 0:
        return "is empty (0 bytes)"
    if not cv2.haveImageReader(str(path)):
        return "is not an image (no image format that OpenCV reads starts like it)"
    return None


def load_image(path: str | Path) -> np.ndarray:
    """Read an image file as an RGB uint8 HxWx3 array; raise naming the path if cv2 cannot."""
    path = Path(path)
    problem = image_file_problem(path)
    if problem == "not found":
        raise FileNotFoundError(f"image {path} not found")
    if problem is not None:
        raise ValueError(f"image {path} {problem}")
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ValueError(f"image {path} cannot be decoded (cv2.imread returned None: truncated or corrupt)")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
