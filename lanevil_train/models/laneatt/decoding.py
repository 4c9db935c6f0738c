"""Which points of a LaneATT proposal make its lane (``model.decode.lane_points``, LANE_POINTS).

A proposal is an x per anchor row (bottom row first, input pixels), the anchor's start row and a predicted length in
rows. Two rules:

- ``inside`` (this project's): the rows from the start up to start + round(length) - 1 (halves up), extended below
  the start while x stays in [0, W - 1]; only the points inside the image are kept, plus the exact point where the
  lane crosses the border between two rows (lanes.row_proposal_to_lane).
- ``official``: the official LaneATT's proposals_to_pred (the facts in models/laneatt/official.py): the length
  rounded half to even, the end capped at the top row, the rows below the start kept while x / W (in float32, as
  the official divides its float32 proposal) stays in [0, 1] (x = W included), and every point of the proposal's
  rows whose x >= 0 kept, right of the image too; no border point added. Its index arithmetic is kept as it is: an
  end below the start (a length under 1) clears the rows from end + 1 on, which a negative end + 1 counts from the
  top row (a length of -1 at the bottom row clears the top row only).
"""

from __future__ import annotations

import numpy as np

from lanevil_train.lanes import as_lane

LANE_POINTS = ("inside", "official")
_CLEARED = -2.0  # what the official writes over the x of a row it drops


def check_lane_points(rule: str) -> str:
    """`rule` if it is one of LANE_POINTS, else a ValueError naming model.decode.lane_points."""
    if rule not in LANE_POINTS:
        raise ValueError(f"model.decode.lane_points={rule!r}: expected one of {', '.join(LANE_POINTS)}")
    return rule


def official_lane_points(xs: np.ndarray, ys: np.ndarray, start: int, length: float,
                             width: int) -> np.ndarray | None:
    """The points the official proposals_to_pred keeps of one proposal (see the module docstring), as a lane
    (N, 2) in input pixels, y descending; None when it keeps fewer than 2.

    xs: (S,) float32 x per row, bottom row first; ys: (S,) y of the rows; start: the anchor's start row; length:
    the predicted length in rows (unrounded)."""
    xs = np.asarray(xs, dtype=np.float32)
    n_rows = len(xs)
    fraction = xs / np.float32(width)  # the official's lane[5:] / img_w, float32
    end = min(start + int(np.round(length)) - 1, n_rows - 1)  # np.round: halves to even, as torch.round
    below = fraction[:start]
    # below the start: kept while every row from it up to the start is inside [0, 1]
    inside_run = ((below >= 0.0) & (below <= 1.0))[::-1].cumprod()[::-1].astype(bool)
    fraction = fraction.copy()
    fraction[end + 1:] = _CLEARED  # the official's slice, negative end + 1 included
    fraction[:start][~inside_run] = _CLEARED
    kept = fraction >= 0.0
    if kept.sum() <= 1:
        return None
    return as_lane(np.stack([xs[kept].astype(np.float64), np.asarray(ys, dtype=np.float64)[kept]], axis=1))
