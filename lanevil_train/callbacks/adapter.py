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
        lanes = _fetch(batch, self.lanes_at, "lanes")
        return np.stack([lane_mask(list(per_image), shape, width) for per_image in lanes])
