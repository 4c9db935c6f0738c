"""Where an illusion lies on the road: the road span (arc lengths from the camera) and the lane of the pixels it
changes in a render, inverse-projected onto the scene's road.

Clips place their camera by it (vlm/clips/clips.py) and the closed loop starts its car 5-10 m before it and times the
attack window from where the car enters it (closed_loop/).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lanevil_train.illusions.visibility import changed_pixels
from lanevil_train.sim import Scene

STANDING = frozenset(("pedestrian", "vehicle", "bicycle", "guard_rail"))  # footprint: lowest pixel per column
MAX_EXTENT_M = 60.0  # the illusion's far end is taken at most this far beyond its near end
FOOTPRINT_THRESHOLD = 24  # RGB-sum change that counts for the footprint: cuts the faint tails of soft edges


@dataclass(frozen=True)
class Footprint:
    """Where the illusion lies on the road of the reference view (arc lengths from its camera)."""

    near_m: float
    far_m: float
    lane: str
    found: bool  # False: no changed pixel on the road (fallback values)



def footprint(scene: Scene, clean: np.ndarray, perturbed: np.ndarray, standing: bool = False) -> Footprint:
    """Near/far end and lane of what changed between two renders of `scene`, inverse-projected onto
    its road (standing objects: the lowest changed pixel of each column)."""
    s, d = changed_road_points(scene, clean, perturbed, standing)
    if len(s) == 0:
        return Footprint(near_m=10.0, far_m=20.0, lane="ego", found=False)
    # one vote per 0.5 m x 0.25 m road cell, so near pixels (many per square metre) do not dominate
    cells = np.unique(np.stack([np.round(s * 2.0), np.round(d * 4.0)], 1), axis=0)
    cs, cd = cells[:, 0] / 2.0, cells[:, 1] / 4.0
    near = float(np.percentile(cs, 1))
    far = float(min(np.percentile(cs, 98), near + MAX_EXTENT_M))
    return Footprint(near_m=near, far_m=max(far, near), lane=lane_of(scene, cd), found=True)


def changed_road_points(scene: Scene, clean: np.ndarray, perturbed: np.ndarray, standing: bool = False,
                        threshold: int = FOOTPRINT_THRESHOLD) -> tuple[np.ndarray, np.ndarray]:
    """Road coordinates (s, d) of the changed pixels of a render of `scene` that hit its road."""
    mask = changed_pixels(clean, perturbed, threshold)
    if standing:
        cols = np.flatnonzero(mask.any(axis=0))
        rows = mask.shape[0] - 1 - np.argmax(mask[::-1, cols], axis=0)
        v, u = rows, cols
    else:
        v, u = np.nonzero(mask)
    pts = scene.ground_hit(u.astype(np.float64), v.astype(np.float64))
    ok = np.all(np.isfinite(pts), axis=1)
    s, d = scene.road_coords(pts[ok, 0], pts[ok, 2])
    return np.asarray(s, np.float64), np.asarray(d, np.float64)


def lane_of(scene: Scene, d: np.ndarray) -> str:
    """Where lateral offsets d lie: 'ego' | 'left' | 'right' | 'left_shoulder' | 'right_shoulder',
    or 'across' when no one place holds 60 % of them."""
    bounds = np.array([b.d for b in scene.road.boundaries])
    ego = scene.params.resolved_ego_lane
    idx = np.searchsorted(bounds, d) - 1  # lane index; -1 left of the road, len(bounds) - 1 right of it
    names = np.where(idx < 0, "left_shoulder", np.where(idx >= len(bounds) - 1, "right_shoulder", np.where(
        idx < ego, "left", np.where(idx > ego, "right", "ego"))))
    labels, counts = np.unique(names, return_counts=True)
    top = int(np.argmax(counts))
    return str(labels[top]) if counts[top] >= 0.6 * counts.sum() else "across"
