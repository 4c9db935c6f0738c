"""The public illusion API: names, categories, apply_illusion, combinations, IllusionTransform, errors."""

from __future__ import annotations

import albumentations as A
import numpy as np
import pytest

from lanevil_train.illusions import (CATEGORIES, ILLUSIONS, GroundPlaneError, IllusionTransform, apply_illusion,
                                     apply_illusions, context_from_scene)
from lanevil_train.sim import SceneParams, build_scene, render_scene

EXPECTED = {
    "road_damage": ("road_crack", "road_repair", "tire_marks", "guard_rail"),
    "traffic_obstruction": ("pedestrian", "vehicle", "bicycle"),
    "shadow": ("streetlight_shadow", "fence_shadow", "rail_shadow", "wire_shadow"),
    "reflection": ("sunlight_reflection", "streetlight_reflection", "vehicle_reflection"),
}
PARAMS = SceneParams(road="straight", num_lanes=3, weather="wet_noon", scene_kind="highway")


def _scene(width=320, height=180, seed=4):
    sample = render_scene(seed, PARAMS, width=width, height=height)
    return sample, context_from_scene(build_scene(seed, PARAMS, width, height))


def test_fourteen_names_in_four_categories():
    assert dict(CATEGORIES) == EXPECTED
    assert len(ILLUSIONS) == 14
    for category, names in EXPECTED.items():
        for name in names:
            assert ILLUSIONS[name].category == category
            assert len(ILLUSIONS[name].levels) == 5


@pytest.mark.parametrize("name", sorted(n for names in EXPECTED.values() for n in names))
def test_every_severity_runs_and_is_deterministic(name):
    sample, ctx = _scene()
    before = sample["image"].copy()
    outs = [apply_illusion(sample["image"], sample["lanes"], name, s, seed=3, context=ctx) for s in range(1, 6)]
    assert np.array_equal(sample["image"], before)  # input untouched
    for severity, out in zip(range(1, 6), outs):
        assert out.shape == before.shape and out.dtype == np.uint8
        again = apply_illusion(sample["image"], sample["lanes"], name, severity, seed=3, context=ctx)
        assert np.array_equal(out, again)
    assert not np.array_equal(outs[-1], before)  # severity 5 visibly changes the image


def test_recovers_the_ground_plane_from_lanes_when_no_context_is_given():
    sample, ctx = _scene(640, 360)
    out = apply_illusion(sample["image"], sample["lanes"], "rail_shadow", 4, seed=1)
    assert out.shape == sample["image"].shape
    assert (out != sample["image"]).any(axis=2).mean() > 0.01


def test_combined_illusions_apply_both():
    sample, ctx = _scene()
    image, lanes = sample["image"], sample["lanes"]
    a = apply_illusion(image, lanes, "fence_shadow", 4, seed=0, context=ctx)
    both = apply_illusions(image, lanes, [("fence_shadow", 4), ("vehicle", 4)], seed=0, context=ctx)
    vehicle_only = apply_illusion(image, lanes, "vehicle", 4, seed=1, context=ctx)
    changed_a = (a != image).any(axis=2)
    changed_both = (both != image).any(axis=2)
    changed_v = (vehicle_only != image).any(axis=2)
    assert changed_both.sum() > changed_a.sum()
    assert not changed_both[~(changed_a | changed_v)].any()  # nothing changes outside the two footprints


def test_bad_names_severities_and_images_are_clear_errors():
    sample, ctx = _scene()
    image, lanes = sample["image"], sample["lanes"]
    with pytest.raises(ValueError, match="unknown illusion 'puddle'.*road_crack"):
        apply_illusion(image, lanes, "puddle", 3, context=ctx)
    for severity in (0, 6, 2.5, "3", True):
        with pytest.raises(ValueError, match="severity must be an integer from 1"):
            apply_illusion(image, lanes, "vehicle", severity, context=ctx)
    with pytest.raises(ValueError, match="uint8 HxWx3"):
        apply_illusion(image.astype(np.float32), lanes, "vehicle", 3, context=ctx)
    with pytest.raises(ValueError, match="uint8 HxWx3"):
        apply_illusion(image[..., 0], lanes, "vehicle", 3, context=ctx)
    with pytest.raises(GroundPlaneError):
        apply_illusion(image, lanes[:1], "vehicle", 3)


def _pipeline(**kwargs):
    return A.Compose([IllusionTransform(**kwargs)], keypoint_params=A.KeypointParams(format="xy", label_fields=["lane_ids"]))


def test_illusion_transform_inside_an_albumentations_pipeline():
    sample, _ = _scene(640, 360)
    points = np.concatenate(sample["lanes"])
    ids = np.concatenate([np.full(len(lane), i) for i, lane in enumerate(sample["lanes"])])
    pipeline = _pipeline(names=["fence_shadow"], severities=(5,), p=1.0)
    pipeline.set_random_seed(0)
    out = pipeline(image=sample["image"], keypoints=points, lane_ids=ids)
    assert (out["image"] != sample["image"]).any()
    np.testing.assert_allclose(np.asarray(out["keypoints"]), points)  # lanes pass along unchanged
    one_lane = ids == 0
    passthrough = _pipeline(names=["fence_shadow"], severities=(5,), p=1.0)(
        image=sample["image"], keypoints=points[one_lane], lane_ids=ids[one_lane])
    assert np.array_equal(passthrough["image"], sample["image"])
    with pytest.raises(GroundPlaneError):
        _pipeline(names=["fence_shadow"], severities=(5,), p=1.0, strict=True)(
            image=sample["image"], keypoints=points[one_lane], lane_ids=ids[one_lane])
    with pytest.raises(ValueError, match="unknown illusion"):
        IllusionTransform(names=["nope"])
