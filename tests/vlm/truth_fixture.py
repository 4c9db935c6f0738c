"""A scene truth dict of the form clips.clip_truth gives, for tests that must not depend on the renderer."""

from __future__ import annotations


def truth(**changes) -> dict:
    """A 3-lane urban left curve, ego in the middle lane, a rail shadow in the left lane; `changes` override."""
    base = dict(road="left_curve", curvature_sign=-1, slope="flat", num_lanes=3, lane_width_m=3.5, ego_lane=1,
                markings=["yellow_double_solid", "white_dashed", "white_dashed", "white_solid"],
                marking_colors=["yellow", "white", "white", "white"], weather="clear_noon", night=False, wet=0.0,
                scene_kind="urban", illusion="rail_shadow", category="shadow", illusion_lane="left",
                illusion_distance_m=[20.0, 18.0, 16.0, 14.0, 12.0, 10.0], ego_speed_mps=12.0, frame_step_m=2.0,
                segment="before", lanes_px=[])
    base.update(changes)
    return base
