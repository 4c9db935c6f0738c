"""LaneATT anchors and ground-truth encoding (numpy only, so it runs in data workers).

Geometry follows the official LaneATT (lucastabelini/LaneATT, lib/models/laneatt.py): straight-line
anchors leave the left, bottom and right image borders (in that order) at Line-CNN's angles,
measured in normalised image coordinates; a lane is x at ``n_offsets`` fixed rows from the bottom
row (row 0) to the top row (y = 0). The anchors are pooled from a feature map of
H // stride rows and W // stride columns, as the official.

How a fraction f of the image becomes pixels (``model.head.fraction_scale``, FRACTION_SCALES):
``last_pixel`` (this project's own configs) f x (W - 1) and f x (H - 1), so the bottom row is y = H - 1 and
f = 1 the last pixel; ``size`` (the official_* experiments) f x W and f x H as the official
(lib/models/laneatt.py l. 36 and 281: rows y = linspace(1, 0, S) x H, the bottom one at y = H, anchor x times
img_w; lib/datasets/lane_dataset.py l. 54: the targets' rows y = H, H - H / (S - 1), ..., 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lanevil_train.models.rows import UNDEFINED_X, encode_lane, pixels_per_unit, row_ys

# Line-CNN's angles as the official lists them (lib/models/laneatt.py, LaneATT.__init__), in degrees
LEFT_ANGLES: tuple[float, ...] = (72.0, 60.0, 49.0, 39.0, 30.0, 22.0)
RIGHT_ANGLES: tuple[float, ...] = (108.0, 120.0, 131.0, 141.0, 150.0, 158.0)
BOTTOM_ANGLES: tuple[float, ...] = (165.0, 150.0, 141.0, 131.0, 120.0, 108.0, 100.0, 90.0, 80.0, 72.0,
                                    60.0, 49.0, 39.0, 30.0, 15.0)
TARGET_META = 3  # target row layout: [valid, start_row, length_rows, x_0 .. x_{S-1}]


def default_origin_counts(image_size: tuple[int, int]) -> tuple[int, int]:
    """Anchor origins per side border and along the bottom: the official 72 / 128 at 360x640, one per 5 px."""
    h, w = image_size
    return max(2, round(h / 5)), max(2, round(w / 5))


@dataclass(frozen=True)
class Anchors:
    """A set of line anchors: x per row (pixels), start row, origin and angle of each."""

    xs: np.ndarray  # (A, S) float64, x at each anchor row (may lie outside the image)
    starts: np.ndarray  # (A,) int64, first row (from the bottom) where the anchor enters the image
    origins: np.ndarray  # (A, 2) normalised (x, y) start point on the border
    angles: np.ndarray  # (A,) degrees

    def __len__(self) -> int:
        return len(self.starts)

    def subset(self, index: np.ndarray) -> "Anchors":
        """The anchors at ``index`` (used for top-k anchor selection)."""
        return Anchors(self.xs[index], self.starts[index], self.origins[index], self.angles[index])


def anchor_x_at(origins: np.ndarray, angles: np.ndarray, ys: np.ndarray, image_size: tuple[int, int],
                scale: str = "last_pixel") -> np.ndarray:
    """x (pixels) of each anchor line at rows ``ys`` (pixels): an (A, len(ys)) array; fractions of the image
    mapped to pixels as `scale` says (FRACTION_SCALES)."""
    h, w = image_size
    yn = np.asarray(ys, dtype=np.float64)[None, :] / pixels_per_unit(h, scale)
    sx, sy = origins[:, :1], origins[:, 1:]
    slope = 1.0 / np.tan(np.deg2rad(angles))[:, None]
    return (sx + (sy - yn) * slope) * pixels_per_unit(w, scale)


def generate_anchors(
    image_size: tuple[int, int],
    n_offsets: int = 72,
    lateral_n: int | None = None,
    bottom_n: int | None = None,
    left_angles: tuple[float, ...] = LEFT_ANGLES,
    right_angles: tuple[float, ...] = RIGHT_ANGLES,
    bottom_angles: tuple[float, ...] = BOTTOM_ANGLES,
    scale: str = "last_pixel",
) -> Anchors:
    """All anchors for an (H, W) input, in the official order: left border origins, bottom, then right.

    Side origins run from the bottom (y = 1) up to the top (y = 0), bottom origins from the right
    (x = 1) to the left (x = 0); each origin carries every angle of its border in turn. `scale`: how
    fractions of the image become pixels (FRACTION_SCALES).
    """
    h, w = image_size
    if h < 2 or w < 2 or n_offsets < 2:
        raise ValueError(f"generate_anchors: need image_size >= (2, 2) and n_offsets >= 2, "
                         f"got {image_size}, {n_offsets}")
    d_lat, d_bot = default_origin_counts(image_size)
    lateral_n = d_lat if lateral_n is None else lateral_n
    bottom_n = d_bot if bottom_n is None else bottom_n
    origins, angles = [], []
    borders = (
        ([(0.0, y) for y in np.linspace(1.0, 0.0, lateral_n)], left_angles),
        ([(x, 1.0) for x in np.linspace(1.0, 0.0, bottom_n)], bottom_angles),
        ([(1.0, y) for y in np.linspace(1.0, 0.0, lateral_n)], right_angles),
    )
    for border_origins, border_angles in borders:
        for origin in border_origins:
            for a in border_angles:
                origins.append(origin)
                angles.append(a)
    origins_arr = np.asarray(origins, dtype=np.float64)
    angles_arr = np.asarray(angles, dtype=np.float64)
    n_strips = n_offsets - 1
    starts = np.clip(np.round((1.0 - origins_arr[:, 1]) * n_strips), 0, n_strips).astype(np.int64)
    xs = anchor_x_at(origins_arr, angles_arr, row_ys(h, n_offsets, scale), image_size, scale)
    return Anchors(xs, starts, origins_arr, angles_arr)


def feature_map_size(image_size: tuple[int, int], stride: int) -> tuple[int, int]:
    """(Hf, Wf) the anchors are pooled from: H // stride, W // stride as the official (fmap_h, fmap_w).

    A ResNet gives ceil(H / stride) rows; the last one (below H // stride) is not read, as in the official."""
    h, w = image_size
    hf, wf = h // stride, w // stride
    if hf < 1 or wf < 1:
        raise ValueError(f"LaneATT: the input {w}x{h} is smaller than the feature stride {stride}")
    return hf, wf


def anchor_cut_indices(anchors: Anchors, image_size: tuple[int, int],
                       stride: int) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """Feature-map column of every anchor at every feature row, and whether it is inside the map.

    Returns (cols (A, Hf) int64 clamped into the map, valid (A, Hf) float32, (Hf, Wf)), built as the
    official compute_anchor_cut_indices: feature row r (top first) is the normalised height
    r / (Hf - 1) (the rows span the whole image, the top one at y = 0, the bottom one at y = H);
    the anchor's x there, in the official scale (normalised x times W), is divided by the stride and
    rounded; a column below 0 or above Wf is zeroed, and the column Wf itself is kept (clamped to
    Wf - 1) as the official's `> fmaps_w` test does.
    """
    h, w = image_size
    hf, wf = feature_map_size(image_size, stride)
    yn = np.linspace(0.0, 1.0, hf) if hf > 1 else np.ones(1)  # official linspace(1, 0, Hf), flipped top-first
    slope = 1.0 / np.tan(np.deg2rad(anchors.angles))[:, None]
    x = (anchors.origins[:, :1] + (anchors.origins[:, 1:] - yn[None, :]) * slope) * w
    cols = np.round(x / stride)
    valid = (cols >= 0) & (cols <= wf)
    return np.clip(cols, 0, wf - 1).astype(np.int64), valid.astype(np.float32), (hf, wf)


def encode_lanes(lanes: list[np.ndarray], image_size: tuple[int, int], n_offsets: int, max_lanes: int,
                 scale: str = "last_pixel") -> np.ndarray:
    """Ground-truth lanes -> float32 (max_lanes, 3 + n_offsets) rows [valid, start, length, xs...] (`scale`: the
    rows' and the image's pixels, FRACTION_SCALES)."""
    out = np.zeros((max_lanes, TARGET_META + n_offsets), dtype=np.float32)
    out[:, TARGET_META:] = UNDEFINED_X
    encoded = []
    for lane in lanes:
        enc = encode_lane(np.asarray(lane), image_size, n_offsets, scale)
        if enc is not None:
            encoded.append(enc)
    if len(encoded) > max_lanes:
        raise ValueError(
            f"encode: {len(encoded)} lanes inside the {image_size[1]}x{image_size[0]} image but max_lanes={max_lanes}; "
            "raise the head's max_lanes"
        )
    for i, (start, length, xs) in enumerate(encoded):
        out[i, 0] = 1.0
        out[i, 1] = start
        out[i, 2] = length
        out[i, TARGET_META:] = xs
    return out
