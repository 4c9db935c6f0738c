"""vlm.clips.clips: clips of a driving camera, clean and perturbed, and their ground truth."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from lanevil_train.illusions import get_illusion
from lanevil_train.illusions.context import context_for_frame
from lanevil_train.illusions.visibility import changed_pixels
from lanevil_train.sim import render_scene, sample_scene_params
from lanevil_train.sim.sequence import scene_at
from lanevil_train.taxonomy import ILLUSION_NAMES
from lanevil_train.vlm.clips import clips
from lanevil_train.vlm.clips.clips import (
    FRAMES_PER_CLIP,
    SEGMENTS,
    ClipCase,
    changed_road_points,
    clip_cases,
    clip_truth,
    lane_of,
    reference_scene,
    render_clip,
    segment_positions,
)

SIZE = (144, 256)


def test_clip_cases_cycle_through_the_illusions():
    cases = clip_cases(5, 1000, ["road_crack", "vehicle"])
    assert [c.case_id for c in cases] == [f"clip-{1000 + i}" for i in range(5)]
    assert [c.illusion for c in cases] == ["road_crack", "vehicle"] * 2 + ["road_crack"]
    assert {c.illusion for c in clip_cases(14, 0, ILLUSION_NAMES)} == set(ILLUSION_NAMES)
    with pytest.raises(ValueError, match=r"illusions\[1\]"):
        clip_cases(2, 0, ["road_crack", "puddle"])


def test_bad_arguments_are_named():
    case = ClipCase("clip-1", 1, "road_crack")
    with pytest.raises(ValueError, match="segment"):
        render_clip(case, "after", [0], SIZE)
    with pytest.raises(ValueError, match=r"severities\[1\]"):
        render_clip(case, "over", [0, 6], SIZE)
    with pytest.raises(ValueError, match="size"):
        clip_truth(case, "over", (144,))
    with pytest.raises(ValueError, match="unknown illusion"):
        ClipCase("clip-1", 1, "puddle")


def test_clip_is_deterministic():
    case = ClipCase("clip-1000004", 1000004, "tire_marks")
    a = render_clip(case, "over", [0, 3], SIZE)
    clips._reference.cache_clear()  # the second render recomputes the reference view too
    b = render_clip(case, "over", [0, 3], SIZE)
    assert sorted(a) == [0, 3] and all(len(a[s]) == FRAMES_PER_CLIP for s in a)
    for sev in a:
        for fa, fb in zip(a[sev], b[sev]):
            assert fa.shape == (*SIZE, 3) and fa.dtype == np.uint8
            assert np.array_equal(fa, fb)
    assert not np.array_equal(a[0][0], a[0][-1])  # the camera moves


@pytest.mark.parametrize("name", ["road_repair", "vehicle", "rail_shadow"])
def test_perturbed_frames_differ_from_clean_only_where_the_illusion_acts(name):
    case = ClipCase("clip-1000002", 1000002, name)
    frames = render_clip(case, "over", [0, 2, 5], SIZE)
    scene = reference_scene(case, SIZE)
    ref_clean = clips._reference(case.seed, name, SIZE)[0]
    positions = segment_positions(case, "over", SIZE)
    for i, s0 in enumerate(positions):
        clean = frames[0][i]
        assert np.array_equal(clean, render_scene_at(scene, s0))
        for sev in (2, 5):
            pert = frames[sev][i]
            # the same illusion, same seed, drawn from this pose into this clean frame
            expected = get_illusion(name)(clean, context_for_frame(scene, float(s0), ref_clean), sev, case.seed)
            assert np.array_equal(pert, expected)
            touched = cv2.dilate((np.abs(pert.astype(int) - clean.astype(int)).sum(2) > 0).astype(np.uint8),
                                 np.ones((9, 9), np.uint8))
            assert np.array_equal(pert[touched == 0], clean[touched == 0])
    assert any(changed_pixels(c, p).mean() > 0.002 for c, p in zip(frames[0], frames[5]))


def render_scene_at(scene, s0):
    from lanevil_train.sim import shade_scene
    return shade_scene(scene_at(scene, float(s0)))


@pytest.mark.parametrize("name,segment,standing", [("road_repair", "over", False), ("tire_marks", "before", False),
                                                    ("vehicle", "over", True)])
def test_illusion_stays_put_on_the_road_while_the_camera_advances(name, segment, standing):
    size = (288, 512)  # far away a row spans metres (and soft edges blur further): measure 3.5-16 m ahead
    case = ClipCase("clip-1000000", 1000000, name)
    frames = render_clip(case, segment, [0, 3], size)
    scene = reference_scene(case, size)
    positions = segment_positions(case, segment, size)
    assert np.all(np.diff(positions) > 3.0)  # metres driven between frames
    near = []
    for s0, clean, pert in zip(positions, frames[0], frames[3]):
        s, _ = changed_road_points(scene_at(scene, float(s0)), clean, pert, standing)
        ahead = float(np.percentile(s, 1)) if len(s) else np.inf
        if 3.5 <= ahead <= 16.0:
            near.append(ahead + float(s0))  # near end in reference arc length
    assert len(near) >= 2  # the camera drives 4-6 m between frames, the illusion moves < 1.5 m
    assert np.ptp(near) < 1.5, near


def test_clip_truth_matches_the_renderer():
    case = ClipCase("clip-1000003", 1000003, "road_crack")
    truth = clip_truth(case, "before", SIZE)
    json.dumps(truth)  # plain JSON values
    params = sample_scene_params(case.seed)
    scene = reference_scene(case, SIZE)
    positions = segment_positions(case, "before", SIZE)
    assert truth["road"] == params.road == "left_curve" and truth["curvature_sign"] == -1
    assert truth["num_lanes"] == params.num_lanes and truth["ego_lane"] == params.resolved_ego_lane
    assert truth["markings"] == list(params.resolved_markings)
    assert truth["marking_colors"] == [("yellow" if m.startswith("yellow") else "none" if m == "none" else "white")
                                       for m in params.resolved_markings]
    assert truth["frame_s_m"] == pytest.approx(list(positions), abs=0.01)
    step = truth["frame_step_m"]
    assert np.diff(truth["illusion_distance_m"]) == pytest.approx([-step] * 5, abs=0.02)
    assert min(truth["illusion_distance_m"]) >= 9.9  # before: the illusion is ahead in every frame
    # lanes: the GT polylines of each clean frame, as the renderer gives them
    for s0, lines, count in zip(positions, truth["lanes_px"], truth["num_lane_lines"]):
        frame = scene_at(scene, float(s0))
        gt = frame.lanes()[0]
        assert count == len(gt) == len(lines)
        for a, b in zip(lines, gt):
            np.testing.assert_allclose(np.asarray(a), b, atol=0.051)
    assert truth["num_lane_lines"][0] == sum(m != "none" for m in params.resolved_markings)
    # the first frame of the reference-free case: the renderer's own lanes at the reference pose
    assert len(render_scene(case.seed, params, SIZE[1], SIZE[0])["lanes"]) == len(scene.lanes()[0])


def test_lane_of_names_where_offsets_lie():
    scene = reference_scene(ClipCase("clip-1000000", 1000000, "road_crack"), SIZE)
    b = [x.d for x in scene.road.boundaries]
    ego = scene.params.resolved_ego_lane
    mid = lambda i: (b[i] + b[i + 1]) / 2  # noqa: E731
    assert lane_of(scene, np.full(10, mid(ego))) == "ego"
    assert lane_of(scene, np.full(10, b[0] - 0.3)) == "left_shoulder"
    assert lane_of(scene, np.full(10, b[-1] + 0.3)) == "right_shoulder"
    if ego > 0:
        assert lane_of(scene, np.full(10, mid(ego - 1))) == "left"
    if ego < len(b) - 2:
        assert lane_of(scene, np.full(10, mid(ego + 1))) == "right"
    assert lane_of(scene, np.r_[np.full(5, b[0] - 0.3), np.full(5, b[-1] + 0.3)]) == "across"


@pytest.mark.parametrize("segment", SEGMENTS)
def test_segments_see_the_illusion_ahead_then_reach_it(segment):
    case = ClipCase("clip-1000001", 1000001, "fence_shadow")
    dist = clip_truth(case, segment, SIZE)["illusion_distance_m"]
    if segment == "before":
        assert min(dist) >= 9.9
    elif segment == "over":
        assert dist[2] > 0 > dist[3]  # the camera reaches the near end between frames 2 and 3
    else:
        assert dist[0] < dist[2] < 0 or dist[-1] < 0
