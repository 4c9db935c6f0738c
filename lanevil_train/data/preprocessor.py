"""The one place an image of any size becomes a detector's input, and its decoded lanes come back to that image.

A model's geometry and pixel conventions are four settings (its build config records them, models/factory.py
DetectorSpec): the input size (H, W), the fraction of the image's height cut from the top first (``crop_top``, as
CLRNet's and UFLD's cut_height), the normalisation preset (data/normalization.py) and the resize filter
(data/resize.py). ``Preprocessor`` holds them: ``image()`` turns a uint8 HxWx3 image (BGR as OpenCV reads it, or RGB)
into the float32 3xHxW input, ``batch()`` stacks several, ``to_image()`` maps lanes decoded in input pixels back to
the original image's pixels. Training and evaluation samples go through the same settings with their labels
(``sample_processor()``: transforms.LaneSampleProcessor).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from lanevil_train.data.normalization import DEFAULT_NORMALIZATION, normalization, normalize_image
from lanevil_train.data.resize import DEFAULT_RESIZE, resize_filter, resize_image
from lanevil_train.data.transforms import LaneSampleProcessor, clip_lane_to_image, crop_lane_rows, crop_rows
from lanevil_train.lanes import scale_lanes

COLOR_ORDERS = ("bgr", "rgb")


def lanes_to_original(lanes: Sequence[np.ndarray], input_size: tuple[int, int], original_size: tuple[int, int],
                      crop_top: float) -> list[np.ndarray]:
    """Lanes in input pixels (an image resized to input_size after crop_top of its height was cut) in the pixels of
    the original image of original_size (H, W): x * W / w, y * (H - cut) / h + cut, cut = round(crop_top * H)."""
    in_h, in_w = input_size
    h, w = original_size
    cut = int(round(crop_top * h))
    return [lane + np.array([0.0, cut]) for lane in scale_lanes(list(lanes), w / in_w, (h - cut) / in_h)]


def lanes_to_input(lanes: Sequence[np.ndarray], original_size: tuple[int, int], input_size: tuple[int, int],
                   crop_top: float) -> list[np.ndarray]:
    """Lanes of an original image of original_size (H, W) in input pixels, as a sample's labels reach the network
    without augmentation (the inverse of lanes_to_original): the top crop_top of the height cut, each lane cut at the
    border of what is left (transforms.clip_lane_to_image), then scaled to input_size; a lane left with fewer than 2
    points is dropped."""
    h, w = original_size
    rows = crop_rows(crop_top, h)
    scale = np.array([input_size[1] / w, input_size[0] / (h - rows)])
    cropped = crop_lane_rows([np.asarray(lane, dtype=np.float64).reshape(-1, 2) for lane in lanes], rows)
    clipped = [clip_lane_to_image(lane, h - rows, w) for lane in cropped]
    return [lane * scale for lane in clipped if len(lane) >= 2]


@dataclass(frozen=True)
class Preprocessor:
    """A model's input geometry and pixel conventions (module docstring); checks them when made."""

    input_size: tuple[int, int]
    crop_top: float = 0.0
    normalize: str = DEFAULT_NORMALIZATION
    resize: str = DEFAULT_RESIZE

    def __post_init__(self) -> None:
        size = tuple(self.input_size)
        if len(size) != 2 or not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= 8
                                     for v in size):
            raise ValueError(f"input_size: expected [height, width], two integers >= 8, got {list(self.input_size)}")
        object.__setattr__(self, "input_size", (int(size[0]), int(size[1])))
        crop_rows(self.crop_top, 1)  # a fraction in [0, 1)
        normalization(self.normalize)
        resize_filter(self.resize)

    def image(self, image: np.ndarray, color: str = "bgr") -> np.ndarray:
        """A uint8 HxWx3 image (`color`: "bgr", as cv2.imread gives it, or "rgb") as the float32 3xHxW input."""
        if color not in COLOR_ORDERS:
            raise ValueError(f"color={color!r}: expected one of {', '.join(COLOR_ORDERS)}")
        image = np.asarray(image)
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(f"expected a uint8 HxWx3 image, got {image.dtype} of shape {image.shape}")
        cut = crop_rows(self.crop_top, image.shape[0])
        # resized before the channels are put in RGB order: the filters act on each channel alone, so the result is
        # the same, and only the network-sized image is reordered (not the whole frame)
        image = resize_image(np.ascontiguousarray(image[cut:]), *self.input_size, self.resize)
        if color == "bgr":
            image = np.ascontiguousarray(image[:, :, ::-1])
        return normalize_image(image, self.normalize)

    def batch(self, images: Sequence[np.ndarray], color: str = "bgr"):
        """Several images (any sizes) as one (B, 3, H, W) float32 tensor."""
        import torch

        return torch.from_numpy(np.stack([self.image(image, color) for image in images]))

    def to_image(self, lanes: Sequence[np.ndarray], original_size: tuple[int, int]) -> list[np.ndarray]:
        """Lanes decoded in input pixels, in the pixels of an original image of (H, W)."""
        return lanes_to_original(lanes, self.input_size, original_size, self.crop_top)

    def sample_processor(self, augment: bool = False, encode: Callable | None = None,
                         extra_transforms: list | None = None) -> LaneSampleProcessor:
        """The processor of labelled samples (images and their lanes) under these settings."""
        return LaneSampleProcessor(self.input_size, augment=augment, encode=encode, extra_transforms=extra_transforms,
                                   crop_top=self.crop_top, normalize=self.normalize, resize=self.resize)
