"""Lane geometry shared by every layer: a lane is an (N, 2) float array of (x, y) pixels.

This is the one currency of the package (every layer hands lanes on in this form): points ordered by
y descending (bottom of the image first). It depends on numpy only, so sim/, data/,
models/ and metrics/ can all use it without importing each other.
"""

from __future__ import annotations

import numpy as np

INVALID_X = -2.0  # TuSimple's marker for "no lane point on this row"

# TuSimple's rows for a 1280x720 image: 160, 170, ..., 710.
TUSIMPLE_H_SAMPLES = np.arange(160, 720, 10, dtype=np.float64)


def as_lane(points, name: str = "lane") -> np.ndarray:
    """Validate and normalise one lane to a float64 (N, 2) array sorted by y descending."""
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"{name}: expected an (N, 2) array of (x, y) points, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: contains non-finite coordinates")
    order = np.argsort(-arr[:, 1], kind="stable")
    return arr[order]


def default_h_samples(height: int) -> np.ndarray:
    """TuSimple-style sample rows for an image of this height (TuSimple's own rows at 720)."""
    return np.round(TUSIMPLE_H_SAMPLES * (height / 720.0))


def lane_x_at(lane: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """x of the lane at each row in ``ys`` by linear interpolation; INVALID_X outside its span."""
    ys = np.asarray(ys, dtype=np.float64)
    out = np.full(ys.shape, INVALID_X)
    if len(lane) == 0:
        return out
    order = np.argsort(lane[:, 1])
    ly, lx = lane[order, 1], lane[order, 0]
    if len(lane) == 1:
        out[ys == ly[0]] = lx[0]
        return out
    inside = (ys >= ly[0]) & (ys <= ly[-1])
    out[inside] = np.interp(ys[inside], ly, lx)
    return out


# How a lane's x is read at given rows (a dataset's h_samples), `model.row_sampling`: what the family's official
# prediction writer does with the lanes its decoding gives.
#   linear: interpolated linearly between the lane's points, INVALID_X outside its span (lane_x_at);
#   spline: the official LaneATT / CLRNet ``Lane`` (LaneATT lib/lane.py:10-23, CLRNet clrnet/utils/lane.py:11-28): an
#     interpolating spline of x over y of degree min(3, N - 1) through the points (scipy's
#     InterpolatedUnivariateSpline), valid within 1 % of the image height past the lane's highest and lowest point,
#     extrapolated there; then the TuSimple writers' ``(xs * img_w).astype(int)`` (LaneATT
#     lib/datasets/tusimple.py:56-62, CLRNet clrnet/datasets/tusimple.py:63-71): x truncated toward zero, INVALID_X
#     where x < 0, any x past the right edge kept;
#   points: x only at the rows where the lane has a point (within POINT_ROW_TOLERANCE px), INVALID_X at every other
#     row: row-wise decoders (UFLD's row anchors, SCNN's rows) whose official writers emit one value per row.
ROW_SAMPLINGS = ("linear", "spline", "points")
SPLINE_MARGIN_FRAC = 0.01   # the Lane's validity margin: 0.01 in y normalised by the image height
POINT_ROW_TOLERANCE = 0.05  # px: a point "at" a row (records keep points to 1e-6 px)


def check_row_sampling(sampling: str, key: str = "model.row_sampling") -> str:
    """`sampling` if it is one of ROW_SAMPLINGS, else a ValueError naming `key`."""
    if sampling not in ROW_SAMPLINGS:
        raise ValueError(f"{key}={sampling!r}: expected one of {', '.join(ROW_SAMPLINGS)}")
    return sampling


def spline_x_at(lane: np.ndarray, ys: np.ndarray, height: float, truncate: bool = True) -> np.ndarray:
    """The official Lane's x at rows ys (see ROW_SAMPLINGS), truncated to whole pixels (as the TuSimple writers;
    not with truncate=False, as the CULane writers); INVALID_X outside its span widened by SPLINE_MARGIN_FRAC *
    height, and where x < 0. Fewer than 2 points: INVALID_X everywhere."""
    from scipy.interpolate import InterpolatedUnivariateSpline

    ys = np.asarray(ys, dtype=np.float64)
    out = np.full(ys.shape, INVALID_X)
    if len(lane) < 2:
        return out
    order = np.argsort(lane[:, 1], kind="stable")
    ly, lx = lane[order, 1], lane[order, 0]
    keep = np.concatenate([[True], np.diff(ly) > 0])  # the spline needs strictly increasing y
    ly, lx = ly[keep], lx[keep]
    if len(ly) < 2:
        return out
    xs = InterpolatedUnivariateSpline(ly, lx, k=min(3, len(ly) - 1))(ys)
    margin = SPLINE_MARGIN_FRAC * float(height)
    valid = (ys >= ly[0] - margin) & (ys <= ly[-1] + margin) & (xs >= 0)
    out[valid] = np.trunc(xs[valid]) if truncate else xs[valid]
    return out


def point_x_at(lane: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """x of the lane's point at each row in ys (within POINT_ROW_TOLERANCE); INVALID_X where it has none."""
    ys = np.asarray(ys, dtype=np.float64)
    out = np.full(ys.shape, INVALID_X)
    if len(lane) == 0:
        return out
    distance = np.abs(lane[None, :, 1] - ys[:, None])
    nearest = distance.argmin(axis=1)
    at_row = distance[np.arange(len(ys)), nearest] <= POINT_ROW_TOLERANCE
    out[at_row] = lane[nearest[at_row], 0]
    out[out < 0] = INVALID_X
    return out


def sample_lane(lane: np.ndarray, ys: np.ndarray, sampling: str = "linear", height: float | None = None) -> np.ndarray:
    """x of one lane at rows ys, read as `sampling` says (ROW_SAMPLINGS); `height` (the image's) for "spline"."""
    if check_row_sampling(sampling) == "points":
        return point_x_at(lane, ys)
    if sampling == "spline":
        if height is None:
            raise ValueError("row sampling 'spline' needs the image height (its validity margin is 1 % of it)")
        return spline_x_at(lane, ys, height)
    return lane_x_at(lane, ys)


def lane_at_rows(lane: np.ndarray, rows, sampling: str, height: float, width: float) -> np.ndarray:
    """The lane's points at `rows` (original pixels), read as `sampling` says (the spline not truncated), where x
    lies in [0, width): what the official CULane writers write for a spline lane (LaneATT lib/datasets/culane.py:
    115-129, CLRNet clrnet/datasets/culane.py:96-110: ``(xs >= 0) & (xs < 1)`` in normalised x). y descending."""
    ys = np.asarray(rows, dtype=np.float64)
    if sampling == "spline":
        xs = spline_x_at(lane, ys, height, truncate=False)
    else:
        xs = sample_lane(lane, ys, sampling)
    keep = (xs >= 0) & (xs < width)
    return as_lane(np.stack([xs[keep], ys[keep]], axis=1))


def check_culane_rows(rows, key: str = "model.culane_rows") -> tuple[float, float, float] | None:
    """None, or [start, stop, step] (numpy.arange's, original pixels, stop excluded) with step > 0 and a row in it."""
    if rows is None:
        return None
    values = list(rows) if isinstance(rows, (list, tuple)) or hasattr(rows, "__len__") else [rows]
    if (len(values) != 3 or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)
            or not values[2] > 0 or not values[1] > values[0]):
        raise ValueError(f"{key}={rows!r}: expected null (each lane's own points) or [start, stop, step], the rows "
                         f"numpy.arange(start, stop, step) gives, with step > 0 and stop > start")
    return tuple(float(v) for v in values)


def culane_lanes(lanes: list[np.ndarray], culane_rows, sampling: str, height: float, width: float) -> list[np.ndarray]:
    """The lanes as a CULane .lines.txt gets them: each lane's own points (culane_rows None), or the lane read at
    numpy.arange(*culane_rows) as `sampling` says, x within [0, width) (lane_at_rows); lanes left with no point
    dropped, as the official writers drop an empty line."""
    if culane_rows is None:
        return list(lanes)
    rows = np.arange(*culane_rows)
    out = [lane_at_rows(lane, rows, sampling, height, width) for lane in lanes]
    return [lane for lane in out if len(lane)]


def lanes_to_rows(lanes: list[np.ndarray], ys: np.ndarray, sampling: str = "linear",
                  height: float | None = None) -> np.ndarray:
    """Lanes as a (L, len(ys)) array of x per row (INVALID_X where a lane has no point), read as `sampling`."""
    if not lanes:
        return np.zeros((0, len(ys)))
    return np.stack([sample_lane(lane, ys, sampling, height) for lane in lanes])


def rows_to_lane(xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Inverse of lane_x_at: keep the rows with a valid x, ordered by y descending."""
    xs = np.asarray(xs, dtype=np.float64)
    ys = np.asarray(ys, dtype=np.float64)
    valid = xs >= 0
    return as_lane(np.stack([xs[valid], ys[valid]], axis=1))


def scale_lanes(lanes: list[np.ndarray], sx: float, sy: float) -> list[np.ndarray]:
    """Lanes in a resized image: x scaled by sx, y by sy."""
    return [lane * np.array([sx, sy]) for lane in lanes]


# How far lane points may lie outside the image, as a fraction of its width / height. CULane's ground
# truth extends each lane's spline to the bottom row, so x there can be far outside the image
# (negative at the left, beyond the width at the right; an outer lane several hundred pixels out);
# y stays within the rows (CULane writes y = 590 on its 590-row images, so the edge itself counts).
# Beyond these margins, or with no point inside the image at all, a lane is taken as given in other
# pixel coordinates (another image size, x and y swapped) and rejected.
LANE_X_MARGIN_FRAC = 1.0       # x in [-width, 2 * width]
LANE_Y_MARGIN_FRAC = 0.02      # y in [-2 %, 102 %] of the height


def lane_extent_problem(points: np.ndarray, height: int, width: int) -> str | None:
    """None if a lane's (N, 2) points fit an image of this size (see LANE_X_MARGIN_FRAC), else why not.

    The answer reads after a lane's name ("lanes[2]: " + problem): it gives the offending points' extent,
    the image size and the accepted ranges. TuSimple's x = INVALID_X ("no point") must be removed first.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if len(pts) == 0:
        return None
    h, w = height, width
    x, y = pts[:, 0], pts[:, 1]
    mx, my = LANE_X_MARGIN_FRAC * w, LANE_Y_MARGIN_FRAC * h
    inside = (x >= 0) & (x <= w) & (y >= 0) & (y <= h)
    far = (x < -mx) | (x > w + mx) | (y < -my) | (y > h + my)
    if not inside.any():
        problem, bad = f"none of its {len(pts)} points lies in the image ({w} wide, {h} high): they", pts
    elif far.any():
        problem, bad = (f"{int(far.sum())} of its {len(pts)} points lie too far outside the image ({w} wide, "
                        f"{h} high): those"), pts[far]
    else:
        return None
    return (f"{problem} span x {bad[:, 0].min():.1f}..{bad[:, 0].max():.1f}, y {bad[:, 1].min():.1f}.."
            f"{bad[:, 1].max():.1f}; expected (x, y) pixels of this image: at least one point in x 0..{w}, y 0..{h} "
            f"and every point within x {-mx:g}..{w + mx:g}, y {-my:g}..{h + my:g}. Are the lanes for another image "
            f"size, or (y, x) pairs?")


def row_proposal_to_lane(xs: np.ndarray, ys: np.ndarray, start: int, end: int, width: int) -> np.ndarray | None:
    """x per row (pixels) from row `start` to `end` -> a lane (N, 2), y descending, or None (< 2 points).

    As LaneATT's and CLRNet's official code, a prediction that starts above the bottom is extended down while
    its x stays inside the image. Only points inside the image are kept, plus the exact border crossing where
    the lane leaves it between two rows, so evaluation rows near the border stay covered."""
    if end < start:
        return None
    inside = (xs >= 0) & (xs <= width - 1)
    lo = start
    while lo > 0 and inside[lo - 1]:
        lo -= 1
    pts = [(xs[k], ys[k]) for k in range(lo, end + 1) if inside[k]]
    for k0 in range(max(lo - 1, 0), end):
        k1 = k0 + 1
        if inside[k0] != inside[k1]:
            out_k = k1 if inside[k0] else k0
            border = 0.0 if xs[out_k] < 0 else width - 1.0
            t = (border - xs[k0]) / (xs[k1] - xs[k0])
            if 0.0 < t < 1.0:
                pts.append((border, ys[k0] + t * (ys[k1] - ys[k0])))
    if len(pts) < 2:
        return None
    return as_lane(np.asarray(pts))


# How lanes are given fixed output slots by the heads that have them (UFLD, SCNN): see assign_slots.
SLOT_ASSIGNMENTS = ("ego", "packed")


def assign_slots(bottom_xs, width: int, max_lanes: int, mode: str = "ego") -> list[int]:
    """The slot of each lane, given the lanes' bottom x sorted left to right; strictly increasing in
    0..max_lanes-1.

    "packed": slots 0, 1, ... left to right. "ego": the lanes keep their left-to-right order but sit around the
    image centre column (the camera), as the datasets' fixed lane indices (left-left, left, right, right-right):
    the lanes left of the centre end at slot max_lanes // 2 - 1, shifted only as far as needed to fit all of them
    (a side with more lanes than its slots spills into the other side's free slots instead of losing lanes).
    """
    if mode not in SLOT_ASSIGNMENTS:
        raise ValueError(f"slot_assignment={mode!r}: expected one of {', '.join(SLOT_ASSIGNMENTS)}")
    n = len(bottom_xs)
    if n > max_lanes:
        raise ValueError(f"{n} lanes, but max_lanes={max_lanes}")
    if mode == "packed" or n == 0:
        return list(range(n))
    n_left = sum(1 for x in bottom_xs if x < (width - 1) / 2.0)
    start = min(max(max_lanes // 2 - n_left, 0), max_lanes - n)
    return list(range(start, start + n))
