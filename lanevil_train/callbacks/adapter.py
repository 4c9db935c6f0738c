"""Where images and lane ground truth sit in a training batch, so defenses work on any LightningModule.

A location is a dict key (str), a position in a tuple/list batch (int), or a callable(batch) -> value.
Lane ground truth is either lanes (per image, a list of (N, 2) x, y arrays in input pixels) or a lane
mask tensor (B, H, W) or (B, 1, H, W) whose non-zero pixels are lane.
"""

from __future__ import annotations

from typing import Any, Callable, Union

import numpy as np
import torch

from lanevil_train.callbacks.regions import lane_mask

Location = Union[str, int, Callable[[Any], Any]]


def _fetch(batch: Any, where: Location, what: str) -> Any:
    if callable(where):
        return where(batch)
    try:
        return batch[where]
    except (KeyError, IndexError, TypeError) as error:
        kind = type(batch).__name__
        keys = f" (keys: {sorted(batch)})" if isinstance(batch, dict) else ""
        raise KeyError(f"BatchAdapter: the {what} are expected at {where!r} of the {kind} batch{keys}") from error


class BatchAdapter:
    """Says where a batch keeps its images (B, C, H, W) and its lane ground truth.

    The default fits lanevil_train's own batches: images at "images", lanes at "input_lanes". Give at most one of
    `lanes` and `lane_mask`; with neither, lanes are read at "input_lanes":

        BatchAdapter()                                   # lanevil_train batches
        BatchAdapter(images="img", lanes="lanes")        # a dict batch with per-image lanes
        BatchAdapter(images="img", lane_mask="seg")      # a dict batch with a lane mask
        BatchAdapter(images=0, lane_mask=1)              # an (images, mask) tuple batch
        BatchAdapter(images=lambda b: b.x, lanes=lambda b: b.lanes)   # anything else
    """

    DEFAULT_LANES = "input_lanes"

    def __init__(self, images: Location = "images", lanes: Location | None = None,
                 lane_mask: Location | None = None):
        if lanes is not None and lane_mask is not None:
            raise ValueError(f"BatchAdapter: give one of lanes=... and lane_mask=..., not both (got lanes={lanes!r}, "
                             f"lane_mask={lane_mask!r})")
        self.images_at = images
        self.lanes_at = lanes if lanes is not None or lane_mask is not None else self.DEFAULT_LANES
        self.lane_mask_at = lane_mask

    def images(self, batch: Any) -> torch.Tensor:
        """The batch's image tensor itself (edits to it change the batch)."""
        images = _fetch(batch, self.images_at, "images")
        if not isinstance(images, torch.Tensor) or images.ndim != 4:
            shape = tuple(images.shape) if isinstance(images, torch.Tensor) else type(images).__name__
            raise ValueError(f"BatchAdapter: images at {self.images_at!r} must be a (B, C, H, W) tensor, got {shape}")
        return images

    def lane_masks(self, batch: Any, shape: tuple[int, int], width: int) -> np.ndarray:
        """Boolean (B, H, W) lane masks at the image size `shape`; lanes are drawn `width` pixels wide."""
        if self.lane_mask_at is not None:
            mask = _fetch(batch, self.lane_mask_at, "lane masks")
            mask = torch.as_tensor(mask)
            if mask.ndim == 4 and mask.shape[1] == 1:
                mask = mask[:, 0]
            if mask.ndim != 3 or tuple(mask.shape[-2:]) != tuple(shape):
                raise ValueError(f"BatchAdapter: lane masks at {self.lane_mask_at!r} must be (B, H, W) with "
                                 f"(H, W) = {tuple(shape)}, got {tuple(mask.shape)}")
            return mask.detach().cpu().numpy() > 0
        lanes = self._check_lanes(_fetch(batch, self.lanes_at, "lanes"))
        return np.stack([lane_mask(list(per_image), shape, width) for per_image in lanes])

    def _check_lanes(self, lanes: Any) -> Any:
        """Lanes must be, per image, a sequence of (N, 2) x, y point arrays; a mask passed as lanes is refused
        (its rows would be taken for lanes)."""
        expected = "a list of (N, 2) x, y point arrays (input pixels) per image"
        if _looks_like_mask(lanes, batch_level=True):
            raise ValueError(f"BatchAdapter: the lanes at {self.lanes_at!r} are a {_describe(lanes)}, which looks "
                             f"like a lane mask; lanes must be {expected}. Pass a mask as "
                             f"lane_mask={self.lanes_at!r} instead of lanes={self.lanes_at!r}")
        if isinstance(lanes, (str, bytes)) or not hasattr(lanes, "__len__") or not hasattr(lanes, "__iter__"):
            raise ValueError(f"BatchAdapter: the lanes at {self.lanes_at!r} are a {_describe(lanes)}; expected "
                             f"{expected}")
        for i, per_image in enumerate(lanes):
            if _looks_like_mask(per_image, batch_level=False):
                raise ValueError(f"BatchAdapter: the lanes of image {i} at {self.lanes_at!r} are a "
                                 f"{_describe(per_image)}, which looks like a lane mask; lanes must be {expected}. "
                                 f"Pass masks as lane_mask={self.lanes_at!r} instead of lanes={self.lanes_at!r}")
            if isinstance(per_image, (str, bytes, dict)) or not hasattr(per_image, "__iter__"):
                raise ValueError(f"BatchAdapter: the lanes of image {i} at {self.lanes_at!r} are a "
                                 f"{_describe(per_image)}; expected {expected}")
            for j, lane in enumerate(per_image):
                try:
                    points = np.asarray(lane.detach().cpu() if isinstance(lane, torch.Tensor) else lane,
                                        dtype=np.float64)
                except (TypeError, ValueError):
                    points = None
                if points is None or points.ndim != 2 or points.shape[1] != 2:
                    raise ValueError(f"BatchAdapter: lane {j} of image {i} at {self.lanes_at!r} is a "
                                     f"{_describe(lane)}; expected {expected}")
        return lanes


def _describe(value: Any) -> str:
    if isinstance(value, (torch.Tensor, np.ndarray)):
        return f"{tuple(value.shape)} {type(value).__name__}"
    return type(value).__name__


def _looks_like_mask(value: Any, batch_level: bool) -> bool:
    """A (B, H, W) / (B, 1, H, W) / (H, W) tensor or array (batch level), or an (H, W) one (one image): not lanes,
    which end in a dimension of 2 (x, y) one level deeper."""
    if not isinstance(value, (torch.Tensor, np.ndarray)) or value.ndim < 2 or value.shape[-1] == 2:
        return False
    if batch_level:
        return value.ndim in (2, 3) or (value.ndim == 4 and value.shape[1] == 1)
    return value.ndim == 2 or (value.ndim == 3 and value.shape[0] == 1)
