"""Image + lane transforms: albumentations pipelines that move the lanes with the image.

Lanes travel as keypoints labelled with their lane index; points pushed out of the image are
dropped, and the lanes are rebuilt, re-sorted by y descending and re-ordered left to right
(a horizontal flip reverses lane order).

Labels may hold points outside the image (CULane extends every lane to the bottom row, so x there is
often negative or beyond the width), which albumentations rejects. Before the pipeline each lane is
therefore cut at the image border (`clip_lane_to_image`): the part outside is replaced by the point
where the lane crosses the border, found by linear interpolation along the polyline, so the lane
inside the image keeps its exact geometry (and its bottom end, from which the target encoders
extrapolate down, lies on the lane).
"""

from __future__ import annotations

from typing import Callable

import albumentations as A
import numpy as np

from lanevil_train.data.normalization import DEFAULT_NORMALIZATION, normalization, normalize_image
from lanevil_train.data.resize import DEFAULT_RESIZE, resize_filter, resize_transform
from lanevil_train.lanes import as_lane


def build_pipeline(input_size: tuple[int, int], augment: bool, extra: list | None = None,
                   resize: str = DEFAULT_RESIZE) -> A.Compose:
    """Resize to the network input (H, W), with photometric and mild geometric augmentation when asked.

    `extra` transforms (e.g. a defense's data augmentation) run before the resize; `resize` names its filter
    (data/resize.py: `area`, the default, has no aliasing when shrinking).
    """
    height, width = input_size
    steps: list = []
    if augment:
        steps += [
            A.HorizontalFlip(p=0.5),
            A.Affine(scale=(0.9, 1.1), translate_percent=(-0.05, 0.05), rotate=(-5, 5), p=0.6),
            A.RandomBrightnessContrast(brightness_limit=0.25, contrast_limit=0.25, p=0.6),
            A.HueSaturationValue(hue_shift_limit=8, sat_shift_limit=20, val_shift_limit=15, p=0.4),
        ]
    steps += list(extra or [])
    steps.append(resize_transform(height, width, resize))
    return A.Compose(steps, keypoint_params=A.KeypointParams(format="xy", label_fields=["lane_ids"]))


# How far inside the far borders (x = width, y = height) a cut lane ends: albumentations wants x < width.
_EDGE = 1e-3


def _clip_segment(p0: np.ndarray, p1: np.ndarray, xmax: float, ymax: float) -> tuple[np.ndarray, np.ndarray] | None:
    """The part of segment p0 -> p1 inside [0, xmax] x [0, ymax] (Liang-Barsky), or None if none is.

    Ends already inside come back unchanged (the same values), so a lane wholly inside is untouched."""
    d = p1 - p0
    t0, t1 = 0.0, 1.0
    for p, q in ((-d[0], p0[0]), (d[0], xmax - p0[0]), (-d[1], p0[1]), (d[1], ymax - p0[1])):
        if p == 0:
            if q < 0:
                return None
            continue
        t = q / p
        if p < 0:
            t0 = max(t0, t)
        else:
            t1 = min(t1, t)
        if t0 > t1:
            return None
    return (p0 if t0 == 0.0 else p0 + t0 * d), (p1 if t1 == 1.0 else p0 + t1 * d)


def clip_lane_to_image(lane: np.ndarray, height: int, width: int) -> np.ndarray:
    """A lane (N, 2) cut to the image: points outside are dropped and, where the lane crosses the
    border, the crossing point (linear interpolation between the points either side) takes their place.

    Border points on the far edges sit _EDGE inside (x < width, y < height, as albumentations wants).
    A lane that leaves the image and comes back keeps both inside parts, joined at their border points;
    a lane never inside comes back empty (0, 2). Point order is kept.
    """
    lane = np.asarray(lane, dtype=np.float64).reshape(-1, 2)
    xmax, ymax = width - _EDGE, height - _EDGE
    inside = (lane[:, 0] >= 0) & (lane[:, 0] <= xmax) & (lane[:, 1] >= 0) & (lane[:, 1] <= ymax)
    if inside.all():
        return lane
    if len(lane) == 1:
        return lane[inside]
    kept: list[np.ndarray] = []
    for p0, p1 in zip(lane[:-1], lane[1:]):
        part = _clip_segment(p0, p1, xmax, ymax)
        if part is None:
            continue
        for point in part:
            if not kept or not np.array_equal(kept[-1], point):
                kept.append(point)
    return np.array(kept, dtype=np.float64).reshape(-1, 2)


def apply_pipeline(pipeline: A.Compose, image: np.ndarray,
                   lanes: list[np.ndarray]) -> tuple[np.ndarray, list[np.ndarray]]:
    """Run an albumentations pipeline on an image and its lanes; lanes come back in output pixels.

    Lanes are first cut at the image border (clip_lane_to_image): points outside the image never reach
    albumentations, which rejects them."""
    height, width = image.shape[:2]
    lanes = [clip_lane_to_image(lane, height, width) for lane in lanes]
    points = np.concatenate(lanes, axis=0) if lanes else np.zeros((0, 2))
    ids = np.concatenate([np.full(len(lane), i) for i, lane in enumerate(lanes)]) if lanes else np.zeros(0)
    out = pipeline(image=image, keypoints=points, lane_ids=ids)
    kps = np.asarray(out["keypoints"], dtype=np.float64).reshape(-1, 2)
    kept_ids = np.asarray(out["lane_ids"])
    moved = [as_lane(kps[kept_ids == i]) for i in range(len(lanes))]
    moved = [lane for lane in moved if len(lane) >= 2]
    moved.sort(key=lambda lane: lane[0, 0])  # left to right at each lane's lowest point
    return out["image"], moved


def crop_rows(crop_top: float, height: int) -> int:
    """Rows cut from the top of an image of this height (the sky, which holds no lane)."""
    if not 0.0 <= crop_top < 1.0:
        raise ValueError(f"crop_top must be a fraction in [0, 1), got {crop_top}")
    return int(round(crop_top * height))


def crop_lane_rows(lanes: list[np.ndarray], rows: int) -> list[np.ndarray]:
    """Lanes of an image whose top `rows` rows are cut: moved up with it, without their points above the cut; a lane
    left with fewer than 2 points is dropped."""
    moved = [lane[lane[:, 1] >= rows] - np.array([0.0, rows]) for lane in lanes]
    return [lane for lane in moved if len(lane) >= 2]


def crop_top_rows(image: np.ndarray, lanes: list[np.ndarray], rows: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """Drop the top `rows` rows of an image; lanes move up with it and lose their points above the cut."""
    if rows == 0:
        return image, lanes
    return image[rows:], crop_lane_rows(lanes, rows)


class LaneSampleProcessor:
    """Turn a sample into network inputs: crop, transform, normalise, and encode targets with `encode`.

    `encode` is the detector family's own target encoder (lanes in input pixels, meta -> a dict of fixed-shape
    arrays),
    passed in by the task so data/ never imports models/. `crop_top` is the fraction of the image
    height cut from the top before anything else (as CLRNet's and UFLD's cut_height). `normalize` names the
    input normalisation preset (data/normalization.py: the model's build config records the one it trained with),
    `resize` the resize filter (data/resize.py, recorded the same way).
    """

    def __init__(self, input_size: tuple[int, int], augment: bool, encode: Callable | None = None,
                 extra_transforms: list | None = None, crop_top: float = 0.0,
                 normalize: str = DEFAULT_NORMALIZATION, resize: str = DEFAULT_RESIZE):
        self.input_size = tuple(input_size)
        resize_filter(resize)  # validate before building anything
        self.resize = resize
        self.pipeline = build_pipeline(self.input_size, augment, extra_transforms, resize)
        self.encode = encode
        crop_rows(crop_top, 1)  # validate now, not in a data worker
        self.crop_top = crop_top
        normalization(normalize)  # validate now too
        self.normalize = normalize

    def __call__(self, sample: dict) -> dict:
        image, lanes = crop_top_rows(sample["image"], sample["lanes"],
                                     crop_rows(self.crop_top, sample["image"].shape[0]))
        image, lanes = apply_pipeline(self.pipeline, image, lanes)
        item = {
            "image": normalize_image(image, self.normalize),
            "lanes": sample["lanes"],  # ground truth in the original image, for scoring
            "input_lanes": lanes,
            "meta": sample["meta"],
        }
        if self.encode is not None:
            item["target"] = self.encode(lanes, sample["meta"])
        return item
