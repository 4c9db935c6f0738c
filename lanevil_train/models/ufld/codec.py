"""UFLD targets (numpy only, so it runs in data workers): row anchors, grid cells, lane slots, the aux mask.

UFLD (Qin et al., ECCV 2020) describes a lane by the grid cell it crosses on each of a fixed set of rows (the
*row anchors*): every row is split into ``num_cells`` cells, and one extra class, index ``num_cells``, means
"no lane on this row". The official row anchors are pixel rows of the 288-pixel-high paper input (TuSimple:
56 rows, 64 to 284 every 4 px; CULane: 18 rows, 121 to 287); here they are fractions of the input height, so the
same set fits any input size (y = fraction * H, clamped to the last pixel row).

The cell geometry is the official one (cfzd/Ultra-Fast-Lane-Detection, data/dataset.py `_grid_pts`): the cell
positions are ``linspace(0, W - 1, G)`` for G = num_cells, so a cell is (W - 1) / (G - 1) px wide and a lane x
falls into cell floor(x / width); G - 1 cells cover [0, W - 1) and the last cell only x = W - 1 itself. The
official writers (evaluation/eval_wrapper.py at 353df10) turn the classifier's output (griding_num + 1, rows,
lanes) into points as follows; ``official_writer_points`` gives the same points (model.decode.official_writer):

- Both: per row and lane, the arg-max over all griding_num + 1 classes; the last class means no point there
  (l. 67 and 76 TuSimple, l. 27-28 CULane). The location is the expectation of the cell index under a softmax over
  the griding_num cells only, the no-lane class left out (scipy.special.softmax of ``out[:-1]`` in float32, times
  an int64 index, summed in float64; l. 70-74, l. 23-26).
- TuSimple (``generate_tusimple_lines``, l. 64-83, called by ``run_test_tusimple`` l. 98): cells indexed from 0;
  x = int(round((loc + 0.5) * 1280.0 / (griding_num - 1))) (l. 81): whole pixels of a 1280-wide image, rounded
  half to even, never clipped (the last cell's x is 1,286 on a 1280-wide image); -2 on no-lane rows. One value per
  row anchor, written at the h_samples 160, 170, ..., 710 (l. 99-102), which are the row anchors 64, ..., 284 of
  the 288-row input at 720 rows. Every one of the 4 lanes is written, also one with no point at all (all -2).
- CULane (``generate_lines``, l. 9-45, called by ``run_test`` l. 63 with ``localization_type='rel'``,
  ``flip_updown=True`` and ``shape`` the 288x800 input): cells indexed from 1 (l. 24), rows taken bottom first
  (l. 16-17); a lane is written only with more than 2 points (l. 40); each point is x = int(loc * col_sample_w *
  1640 / 800) - 1 with col_sample_w = (800 - 1) / (griding_num - 1) (l. 11-12, 44): truncated toward zero, then
  one pixel left, never clipped; y = int(590 - k * 20) - 1 for the k-th row from the bottom (l. 44): 589, 569,
  ..., 249 for the 18 rows, not the row anchors' own heights (121..287 of 288 rows are 247.9..588.0 of 590; the
  official demo.py l. 89 uses those, the test writer does not).

``cell_to_x`` is the TuSimple writer's mapping, in the input's pixels: our lanes are resized proportionally
(x * W_orig / W), so the same formula gives the same original x. Our own decoding (official_writer null) uses it on
both datasets, as floats clipped to the image, at the row anchors' heights; the official CULane writer's x lies
0-3 px right of it (2.05 / 199 * (399 - loc) - 1 px before its truncation, loc from 0: half a cell at the left
edge, less the -1).
One more small difference: the official encodes in the original image's pixels (cells of (W_orig - 1) / (G - 1)),
we in the input's, which moves a cell boundary by at most a pixel.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from itertools import pairwise

import numpy as np

from lanevil_train.lanes import as_lane, assign_slots, lane_x_at

PAPER_HEIGHT = 288.0  # the official row anchors are pixel rows of a 288x800 input
ROW_ANCHOR_PRESETS: dict[str, tuple[float, ...]] = {
    "tusimple": tuple(float(r) for r in range(64, 285, 4)),  # 56 rows
    "culane": (121.0, 131.0, 141.0, 150.0, 160.0, 170.0, 180.0, 189.0, 199.0, 209.0, 219.0, 228.0, 238.0, 248.0,
               258.0, 267.0, 277.0, 287.0),  # 18 rows
}


def row_anchor_fractions(row_anchors: str | Sequence[float] = "tusimple", num_rows: int | None = None) -> np.ndarray:
    """The row anchors as fractions of the input height, top row first (ascending).

    `row_anchors` is a preset name ("tusimple", "culane": the official rows at 288 px) or a list of fractions in
    [0, 1]; `num_rows`, when given, replaces them by that many rows spread evenly over the same span.
    """
    if isinstance(row_anchors, str):
        if row_anchors not in ROW_ANCHOR_PRESETS:
            raise ValueError(f"row_anchors={row_anchors!r}: expected one of {', '.join(ROW_ANCHOR_PRESETS)} or a list "
                             f"of fractions of the input height")
        fracs = np.asarray(ROW_ANCHOR_PRESETS[row_anchors]) / PAPER_HEIGHT
    elif isinstance(row_anchors, Mapping) or not isinstance(row_anchors, Sequence):
        # a ValueError like every other config error (Hydra passes lists as ListConfig, a Sequence)
        raise ValueError(f"row_anchors: expected a preset name or a list of fractions, got {row_anchors!r}")  # noqa: TRY004
    else:
        fracs = np.asarray([float(f) for f in row_anchors], dtype=np.float64)
        if fracs.ndim != 1 or np.any(fracs < 0) or np.any(fracs > 1) or np.any(np.diff(fracs) <= 0):
            raise ValueError(f"row_anchors: fractions of the height must lie in [0, 1] and increase strictly, got "
                             f"{list(fracs)}")
    if num_rows is not None:
        if int(num_rows) < 3:
            raise ValueError(f"num_rows must be >= 3, got {num_rows}")
        fracs = np.linspace(fracs[0], fracs[-1], int(num_rows))
    if len(fracs) < 3:
        raise ValueError(f"row_anchors: need at least 3 rows (the shape loss spans three), got {len(fracs)}")
    return fracs


def row_ys(fractions: np.ndarray, height: int) -> np.ndarray:
    """The y (input pixels) of each row anchor: fraction * height, at most the last pixel row."""
    return np.minimum(np.asarray(fractions, dtype=np.float64) * height, height - 1.0)


def cell_width(width: int, num_cells: int) -> float:
    """Width in pixels of one grid cell: the spacing of the official cell positions linspace(0, W - 1, G)
    (data/dataset.py `_grid_pts`: col_sample[1] - col_sample[0])."""
    return (width - 1.0) / (num_cells - 1)


def cell_to_x(locations, width: int, num_cells: int):
    """x (pixels) of expected cell indices (numpy or torch): (loc + 0.5) * W / (G - 1), the official TuSimple
    writer's mapping (evaluation/eval_wrapper.py `generate_tusimple_lines`, with W its 1280). It is the cell's
    centre stretched by W / (W - 1): at most one pixel right of it."""
    return (locations + 0.5) * (width / (num_cells - 1.0))


OFFICIAL_WRITERS = ("tusimple", "culane")
TUSIMPLE_WRITER_WIDTH = 1280.0    # eval_wrapper.py l. 81: the x scale of generate_tusimple_lines
CULANE_WRITER_SIZE = (590, 1640)  # eval_wrapper.py l. 44: (height, width) of generate_lines' points
CULANE_WRITER_ROW_STEP = 20       # ... and its rows, 590 - 1 - 20 k, k from the bottom


def official_writer_points(locations, num_rows: int, image_size: tuple[int, int], num_cells: int,
                           writer: str) -> tuple[np.ndarray, np.ndarray | None]:
    """The official writer's (x of each location, y of each row) in the input's pixels (see the module docstring).

    `locations`: expected cell indices from 0 (any shape); `image_size`: the input's (H, W). The x are the
    writer's whole pixels (TuSimple: of a 1280-wide image; CULane: of a 1640x590 one) scaled to the input, so that
    the proportional resize back to the original image gives them again. y: None for "tusimple" (its values sit at
    the row anchors, which its h_samples are), else the CULane writer's rows, top row first, in input pixels
    (the whole image resized to the input, data.crop_top 0, as the official test loader)."""
    h, w = image_size
    locations = np.asarray(locations, dtype=np.float64)
    if writer == "tusimple":
        xs = np.round((locations + 0.5) * TUSIMPLE_WRITER_WIDTH / (num_cells - 1))  # half to even, as round()
        return xs * (w / TUSIMPLE_WRITER_WIDTH), None
    if writer == "culane":
        out_h, out_w = CULANE_WRITER_SIZE
        step = (w - 1.0) / (num_cells - 1)  # col_sample_w: the spacing of linspace(0, W - 1, G)
        xs = np.trunc((locations + 1.0) * step * out_w / w) - 1.0
        ys = out_h - 1.0 - CULANE_WRITER_ROW_STEP * np.arange(num_rows)[::-1]
        return xs * (w / out_w), ys * (h / out_h)
    raise ValueError(f"official_writer={writer!r}: expected null or one of {', '.join(OFFICIAL_WRITERS)}")


def x_to_cell(xs: np.ndarray, width: int, num_cells: int) -> np.ndarray:
    """Cell index of each x, floor(x / cell_width) as the official label code (data/dataset.py `_grid_pts`:
    int(pt // (col_sample[1] - col_sample[0]))); NaN or x outside [0, W - 1] gives num_cells (the "no lane"
    class). The same float arithmetic as the official; the clip only guards the last cell against rounding up."""
    xs = np.asarray(xs, dtype=np.float64)
    inside = np.isfinite(xs) & (xs >= 0) & (xs <= width - 1)
    cells = np.floor(np.where(inside, xs, 0.0) / cell_width(width, num_cells))
    return np.where(inside, np.clip(cells, 0, num_cells - 1), num_cells).astype(np.int64)


def _line_fit(points: np.ndarray) -> tuple[float, float]:
    """(a, b) of x = a * y + b fitted to the points by least squares (two or more distinct y)."""
    a, b = np.polyfit(points[:, 1], points[:, 0], deg=1)
    return float(a), float(b)


def lane_row_xs(lane: np.ndarray, ys: np.ndarray, width: int, height: int,
                extend_to_bottom: bool = True) -> tuple[np.ndarray, float] | None:
    """One lane -> (x at each row anchor, NaN where it has none; its x at the image bottom), or None.

    Inside its annotated span a lane's x is interpolated. Like the official loader, a lane that stops above the
    image bottom is extended straight down by a line fitted to its lower half (`extend_to_bottom`). Rows where
    x leaves [0, W - 1] have none. The bottom x (of the lower-half line, unclipped) orders the lanes left to right.
    """
    lane = as_lane(lane)
    _, first = np.unique(lane[:, 1], return_index=True)
    lane = lane[np.sort(first)]  # distinct y, descending
    if len(lane) < 2:
        return None
    ymin, ymax = lane[-1, 1], lane[0, 1]
    lower = lane[lane[:, 1] >= 0.5 * (ymin + ymax)]
    a_low, b_low = _line_fit(lower if len(lower) >= 2 else lane[:2])
    xs = np.full(len(ys), np.nan)
    span = (ys >= ymin) & (ys <= ymax)
    xs[span] = lane_x_at(lane, ys[span])
    below = ys > ymax
    if extend_to_bottom:
        xs[below] = a_low * ys[below] + b_low
    xs[~(np.isfinite(xs) & (xs >= 0) & (xs <= width - 1))] = np.nan
    if not np.isfinite(xs).any():
        return None
    return xs, a_low * (height - 1.0) + b_low


def encode_cls_labels(lanes: Sequence[np.ndarray], fractions: np.ndarray, image_size: tuple[int, int],
                      num_cells: int, max_lanes: int, slot_assignment: str = "ego",
                      extend_to_bottom: bool = True) -> tuple[np.ndarray, list[tuple[int, np.ndarray]]]:
    """GT lanes -> (int64 (num_rows, max_lanes) cell labels, [(slot, lane points)] of the lanes that got one)."""
    h, w = image_size
    ys = row_ys(fractions, h)
    encoded = []
    for lane in lanes:
        out = lane_row_xs(np.asarray(lane), ys, w, h, extend_to_bottom)
        if out is not None:
            encoded.append((out[1], out[0], as_lane(lane)))
    if len(encoded) > max_lanes:
        raise ValueError(f"encode: {len(encoded)} lanes inside the {w}x{h} image but max_lanes={max_lanes}; raise the "
                         f"head's max_lanes")
    encoded.sort(key=lambda item: item[0])
    slots = assign_slots([e[0] for e in encoded], w, max_lanes, slot_assignment)
    labels = np.full((len(ys), max_lanes), num_cells, dtype=np.int64)
    for slot, (_, xs, _) in zip(slots, encoded):
        labels[:, slot] = x_to_cell(xs, w, num_cells)
    return labels, [(slot, e[2]) for slot, e in zip(slots, encoded)]


def draw_seg_mask(lanes: Sequence[tuple[int, np.ndarray]], image_size: tuple[int, int], stride: int,
                  line_width: int = 1) -> np.ndarray:
    """The aux segmentation target: uint8 (ceil(H / stride), ceil(W / stride)), 0 background, slot + 1 on lane k.

    Each (slot, lane) polyline is drawn at the aux resolution (a pixel's centre maps to input pixel
    (i + 0.5) * stride - 0.5), `line_width` aux pixels wide; where lanes cross, the later slot wins.
    """
    h, w = image_size
    hs, ws = -(-h // stride), -(-w // stride)
    mask = np.zeros((hs, ws), dtype=np.uint8)
    r = (int(line_width) - 1) // 2
    offsets = [(dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1)]
    for slot, lane in lanes:
        pts = (np.asarray(lane, dtype=np.float64) + 0.5) / stride - 0.5  # aux pixel coordinates
        if len(pts) == 1:
            dense = pts
        else:
            parts = []
            for p0, p1 in pairwise(pts):
                n = int(np.ceil(np.abs(p1 - p0).max() * 2)) + 1
                parts.append(p0 + np.linspace(0.0, 1.0, n)[:, None] * (p1 - p0))
            dense = np.concatenate(parts)
        cols, rows = np.round(dense[:, 0]).astype(np.int64), np.round(dense[:, 1]).astype(np.int64)
        for dy, dx in offsets:
            rr, cc = rows + dy, cols + dx
            ok = (rr >= 0) & (rr < hs) & (cc >= 0) & (cc < ws)
            mask[rr[ok], cc[ok]] = slot + 1
    return mask
