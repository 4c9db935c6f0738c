"""Image resize filters (`data.resize`): the filter that brings an image to the network input size, as each
detector family's official test pipeline does it.

  area          OpenCV INTER_AREA (the default: what this project always used; no aliasing when shrinking)
  linear        OpenCV INTER_LINEAR (cv2.resize's and albumentations' Resize default)
  cubic         OpenCV INTER_CUBIC (imgaug's Resize default, "cubic")
  pil_bilinear  PIL Image.resize(BILINEAR) on the uint8 RGB image (torchvision's transforms.Resize on PIL images)

Lanes are scaled the same whatever the filter. The filter a model was trained with is stored in its build config
(`resize`, tasks/builders.model_config) beside `normalize`, so evaluation, export and the closed loop feed a
checkpoint what it learnt on; build configs written before the key existed were all trained on `area`.
"""

from __future__ import annotations

import albumentations as A
import cv2
import numpy as np
from PIL import Image

# name -> OpenCV interpolation flag (None: not OpenCV's)
RESIZE_FILTERS: dict[str, int | None] = {
    "area": cv2.INTER_AREA,
    "linear": cv2.INTER_LINEAR,
    "cubic": cv2.INTER_CUBIC,
    "pil_bilinear": None,
}
DEFAULT_RESIZE = "area"  # what every build config without a `resize` key was trained with


def resize_filter(name: str, key: str = "data.resize") -> str:
    """`name` if it is a filter; else an error naming `key` and the filters."""
    if not isinstance(name, str) or name not in RESIZE_FILTERS:
        raise ValueError(f"{key}: expected one of {', '.join(RESIZE_FILTERS)}, got {name!r}")
    return name


def spec_resize(spec: dict | None) -> str:
    """The filter a model's build config records (`area` for build configs older than the key)."""
    return (spec or {}).get("resize") or DEFAULT_RESIZE


def resize_image(image: np.ndarray, height: int, width: int, name: str = DEFAULT_RESIZE) -> np.ndarray:
    """uint8 HxWx3 RGB image resized to (height, width) with the filter `name`."""
    flag = RESIZE_FILTERS[resize_filter(name)]
    if flag is None:
        return np.asarray(Image.fromarray(np.ascontiguousarray(image)).resize((width, height), Image.BILINEAR))
    return cv2.resize(image, (width, height), interpolation=flag)


class PILBilinearResize(A.Resize):
    """albumentations' Resize (keypoints scaled the same), with the image resized by PIL's bilinear filter."""

    def apply(self, img: np.ndarray, **params) -> np.ndarray:
        return resize_image(img, self.height, self.width, "pil_bilinear")


def resize_transform(height: int, width: int, name: str = DEFAULT_RESIZE) -> A.DualTransform:
    """The albumentations step resizing an image and its lanes to (height, width) with the filter `name`."""
    flag = RESIZE_FILTERS[resize_filter(name)]
    if flag is None:
        return PILBilinearResize(height, width)
    return A.Resize(height, width, interpolation=flag)
