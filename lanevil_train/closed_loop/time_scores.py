"""Time-resolved scores of a closed-loop run: time to line crossing, recovery, and false lane lock.

A trace is a list of control steps {t (s), s (m along the road), d (m from the road's centre line, + right),
deviation (m from the ego lane's centre, + right), heading (rad to the road's tangent, + right), ...}; a lane
keeper's steps also hold the tracked boundaries ahead (closed_loop/lane_keeper.py: left_boundary_m,
right_boundary_m). The attack window is [entry, entry + window] as in run_scores (the paper's 2.5 s).

* Time to line crossing (TLC; Godthelp, Milgram and Blaauw 1984, first order as in van Winsum, Brookhuis and de
  Waard 2000): with the car's deviation y, its lateral speed vy = v sin(heading) (the bicycle model's exact
  dd/dt; v: the step's `speed_mps` where the trace has it, else the run's constant speed) and the margin
  m = lane_width / 2 - half_width (the distance from the car's outer wheel to the line when centred),
      TLC = (m - y) / vy  for vy > 0 (towards the right line),   (m + y) / -vy  for vy < 0 (the left one),
  0 with a wheel already on a line (|y| >= m), infinite for vy = 0 (parallel: it never crosses). TLC values are
  capped at TLC_CAP_S (an infinite one too), so means over runs are defined: beyond a few seconds TLC only says
  "not heading for a line". Scored: at the first step at or after entering the illusion region (tlc_entry_s) and
  its minimum over the attack window's steps (tlc_min_s).
* Recovery: from the first step of the window with |deviation| > threshold (the attack success rule, 0.285 m:
  run_scores.attack_fired_at) to the first later step back within it (recovery_s); recovered False and
  recovery_s None when the car was still out when the run ended (a run ends `after_s` after the window, or when it
  left the road), both None when it never went out.
* False lane lock: a frame of the window where a tracked boundary lies within LOCK_EDGE_M (0.3 m) of an edge of
  the illusion's footprint and farther than LOCK_TRUE_M (0.5 m) from every true lane line (the road's
  boundaries). The tracked boundaries are taken BOUNDARY_AHEAD_M (10 m) ahead of the rear axle in the car's frame
  and mapped onto the road exactly through the road's own geometry at the car's pose (boundaries_on_road: the
  point's s and d, on curves too); the illusion's edges are looked up at that point's s. Scored: lock_frames,
  lock_longest_s (the longest run of consecutive lock frames x the control period) and lock_share (lock frames /
  the window's frames); all None when the trace has no tracked boundaries (a VLM policy, an older trace).
* The illusion's footprint edges (FootprintEdges, illusion_edges): the road points of the pixels the illusion
  changes in the case's reference view at REGION_SEVERITY (illusions.footprint.changed_road_points, as
  episode.illusion_region), once per case and illusion, shared by every severity and the clean twin (so a twin's
  lock frames are its tracker's chance coincidences with the same lines). The points are snapped to cells
  EDGE_CELL_S_M x EDGE_CELL_D_M; at arc length s the cells within EDGE_SPAN_M of s, across d, split where
  EDGE_GAP_M or more is unchanged, give one band each; a band's two sides are its edges (a thin painted line's
  two sides lie close together; a shadow's or a patch's are its long sides).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np

from lanevil_train.closed_loop.lane_keeper import BOUNDARY_AHEAD_M
from lanevil_train.closed_loop.run_scores import (
    ASR_THRESHOLD_M,
    ASR_WINDOW_S,
    HALF_CAR_WIDTH_M,
    attack_fired_at,
    entry_time,
    in_window,
)
from lanevil_train.sim.road import RoadGeometry
from lanevil_train.sim.sequence import road_at

TLC_CAP_S = 10.0
LOCK_EDGE_M = 0.3
LOCK_TRUE_M = 0.5
EDGE_CELL_S_M = 0.5
EDGE_CELL_D_M = 0.1
EDGE_SPAN_M = 1.0
EDGE_GAP_M = 0.25


# ----------------------------------------------------------------------------------------- time to line crossing
def time_to_line_crossing(deviation_m: float, lateral_speed_mps: float, lane_width_m: float,
                          half_width_m: float = HALF_CAR_WIDTH_M) -> float:
    """First-order TLC (s; see the module docstring): the outer wheel's distance to the line the car moves towards
    over its lateral speed (m/s, + right); 0 with a wheel on a line, math.inf when moving parallel."""
    margin = lane_width_m / 2.0 - half_width_m
    if abs(deviation_m) >= margin:
        return 0.0
    if lateral_speed_mps > 0:
        return (margin - deviation_m) / lateral_speed_mps
    if lateral_speed_mps < 0:
        return (margin + deviation_m) / -lateral_speed_mps
    return math.inf


def lateral_speed(step: dict, speed_mps: float) -> float:
    """The car's lateral speed (m/s, + right): v sin(heading), v the step's speed_mps if it has one."""
    return float(step.get("speed_mps", speed_mps)) * math.sin(step["heading"])


def tlc_scores(trace: Sequence[dict], entry_s: float | None, lane_width_m: float, speed_mps: float,
               window_s: float = ASR_WINDOW_S, cap_s: float = TLC_CAP_S) -> dict:
    """{tlc_entry_s, tlc_min_s}: TLC (capped at cap_s) at the first window step and its minimum over the window's
    steps; None without an entry."""
    window = [step for step in trace if entry_s is not None and in_window(step["t"], entry_s, window_s)]
    if not window:
        return {"tlc_entry_s": None, "tlc_min_s": None}
    tlc = [min(time_to_line_crossing(step["deviation"], lateral_speed(step, speed_mps), lane_width_m), cap_s)
           for step in window]
    return {"tlc_entry_s": round(tlc[0], 4), "tlc_min_s": round(min(tlc), 4)}


# ------------------------------------------------------------------------------------------------- recovery
def recovery_scores(trace: Sequence[dict], fired_t: float | None, threshold_m: float = ASR_THRESHOLD_M) -> dict:
    """{recovered, recovery_s}: from fired_t (the first time |deviation| > threshold_m in the window) to the first
    later step with |deviation| <= threshold_m (s); (False, None) if none; (None, None) if it never fired."""
    if fired_t is None:
        return {"recovered": None, "recovery_s": None}
    for step in trace:
        if step["t"] > fired_t + 1e-9 and abs(step["deviation"]) <= threshold_m:
            return {"recovered": True, "recovery_s": round(step["t"] - fired_t, 4)}
    return {"recovered": False, "recovery_s": None}


# ----------------------------------------------------------------------------------------- the footprint's edges
@dataclass(frozen=True)
class FootprintEdges:
    """The illusion's changed road cells (arc length s, lateral offset d: cell centres, m); `at(s)` their edges."""

    s: np.ndarray
    d: np.ndarray

    @classmethod
    def from_points(cls, s, d) -> FootprintEdges:
        """From road points (s, d, m), snapped to EDGE_CELL_S_M x EDGE_CELL_D_M cells, one per cell."""
        s, d = np.asarray(s, np.float64), np.asarray(d, np.float64)
        if s.shape != d.shape:
            raise ValueError(f"FootprintEdges: {s.shape} arc lengths for {d.shape} lateral offsets")
        cells = np.unique(np.stack([np.round(s / EDGE_CELL_S_M), np.round(d / EDGE_CELL_D_M)], 1), axis=0)
        return cls(cells[:, 0] * EDGE_CELL_S_M, cells[:, 1] * EDGE_CELL_D_M)

    def at(self, s: float) -> np.ndarray:
        """The edges' lateral offsets (m, ascending) at arc length s: each band's two sides (module docstring)."""
        d = np.unique(self.d[np.abs(self.s - s) <= EDGE_SPAN_M + 1e-9])
        if not len(d):
            return d
        cuts = np.flatnonzero(np.diff(d) >= EDGE_GAP_M - 1e-9) + 1
        return np.array([side for band in np.split(d, cuts) for side in (band[0], band[-1])])


@lru_cache(maxsize=16)
def illusion_edges(seed: int, illusion: str, size: tuple[int, int]) -> FootprintEdges:
    """The footprint edges of an illusion in a case's reference view at REGION_SEVERITY (module docstring)."""
    from lanevil_train.closed_loop.episode import region_render
    from lanevil_train.illusions.footprint import STANDING, changed_road_points

    return FootprintEdges.from_points(*changed_road_points(*region_render(seed, illusion, size),
                                                           illusion in STANDING))


# ----------------------------------------------------------------------------------------------- false lane lock
def boundaries_on_road(step: dict, road: RoadGeometry, ahead_m: float = BOUNDARY_AHEAD_M
                       ) -> tuple[float, float, float] | None:
    """(s, left d, right d) on the road (m) of a step's tracked boundaries, ahead_m ahead of the rear axle in the
    car's frame; None where it has none. The car's frame (x right, z forward) is turned by its heading from the
    road's tangent at the car: x, z -> X = x cos h + z sin h, Z = z cos h - x sin h in the road's frame at the car's
    pose (sim.sequence.road_at, the centre line at X = -d), where the road's own geometry gives s and d."""
    left, right = step.get("left_boundary_m"), step.get("right_boundary_m")
    if left is None or right is None:
        return None
    posed = replace(road_at(road, step["s"]), x0=-step["d"])
    cos, sin = math.cos(step["heading"]), math.sin(step["heading"])
    x = np.array([left, right], np.float64)
    big_x, big_z = x * cos + ahead_m * sin, ahead_m * cos - x * sin
    d = posed.lateral(big_x, big_z)
    s = step["s"] + float(np.mean(posed.arc_length(big_z)))
    return s, float(d[0]), float(d[1])


def locked(boundary_d: float, edges_d: np.ndarray, lines_d: np.ndarray) -> bool:
    """Whether one tracked boundary (road d, m) is within LOCK_EDGE_M of an illusion edge and farther than
    LOCK_TRUE_M from every true lane line."""
    near_edge = len(edges_d) and np.min(np.abs(edges_d - boundary_d)) <= LOCK_EDGE_M + 1e-9
    off_lines = not len(lines_d) or np.min(np.abs(lines_d - boundary_d)) > LOCK_TRUE_M
    return bool(near_edge and off_lines)


def tracking_series(trace: Sequence[dict], road: RoadGeometry, edges: FootprintEdges,
                    ahead_m: float = BOUNDARY_AHEAD_M) -> list[dict | None]:
    """Per step, {s, left, right (road d, m), edges (the illusion's edges at that s), locked}, or None without
    tracked boundaries: what false_lane_lock counts and report/closed_loop.py plots."""
    lines = np.array([b.d for b in road.boundaries], np.float64)
    out = []
    for step in trace:
        where = boundaries_on_road(step, road, ahead_m)
        if where is None:
            out.append(None)
            continue
        s, left, right = where
        at = edges.at(s)
        out.append({"s": s, "left": left, "right": right, "edges": at,
                    "locked": locked(left, at, lines) or locked(right, at, lines)})
    return out


def _longest_run(flags: Sequence[bool]) -> int:
    longest = current = 0
    for flag in flags:
        current = current + 1 if flag else 0
        longest = max(longest, current)
    return longest


def period_s(trace: Sequence[dict]) -> float:
    """The control period (s): the median time between steps (0 for one step)."""
    return float(np.median(np.diff([step["t"] for step in trace]))) if len(trace) > 1 else 0.0


def false_lane_lock(trace: Sequence[dict], entry_s: float | None, road: RoadGeometry, edges: FootprintEdges,
                    window_s: float = ASR_WINDOW_S, ahead_m: float = BOUNDARY_AHEAD_M) -> dict:
    """{lock_frames, lock_longest_s, lock_share} over the attack window's steps (module docstring); all None
    without an entry or with no tracked boundaries in the trace."""
    none = {"lock_frames": None, "lock_longest_s": None, "lock_share": None}
    window = [step for step in trace if entry_s is not None and in_window(step["t"], entry_s, window_s)]
    if not window or not any("left_boundary_m" in step for step in trace):
        return none
    flags = [bool(item and item["locked"]) for item in tracking_series(window, road, edges, ahead_m)]
    return {"lock_frames": sum(flags), "lock_longest_s": round(_longest_run(flags) * period_s(trace), 4),
            "lock_share": round(sum(flags) / len(flags), 4)}


# --------------------------------------------------------------------------------------------------- together
def time_scores(trace: Sequence[dict], region_start_m: float, lane_width_m: float, speed_mps: float,
                road: RoadGeometry, edges: FootprintEdges, threshold_m: float = ASR_THRESHOLD_M,
                window_s: float = ASR_WINDOW_S) -> dict:
    """A run's time-resolved scores (module docstring): tlc_entry_s, tlc_min_s, recovered, recovery_s,
    lock_frames, lock_longest_s, lock_share. `road`: the case's road (its boundaries are the true lane lines),
    `edges`: the illusion's footprint edges (illusion_edges), `speed_mps`: the constant speed where a step has
    no speed_mps."""
    if not trace:
        raise ValueError("time_scores: an empty trace")
    entry = entry_time(trace, region_start_m)
    fired = attack_fired_at(trace, entry, threshold_m, window_s)
    return {**tlc_scores(trace, entry, lane_width_m, speed_mps, window_s),
            **recovery_scores(trace, fired, threshold_m),
            **false_lane_lock(trace, entry, road, edges, window_s)}
