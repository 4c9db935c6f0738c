"""The public illusion API: names, categories, apply_illusion, combinations, IllusionTransform, errors."""

from __future__ import annotations

import albumentations as A
import numpy as np
import pytest

from lanevil_train.illusions import (
    CATEGORIES,
    ILLUSIONS,
    GroundPlaneError,
    IllusionTransform,
    apply_illusion,
    apply_illusions,
    context_from_scene,
)
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
    return A.Compose([IllusionTransform(**kwargs)],
                     keypoint_params=A.KeypointParams(format="xy", label_fields=["lane_ids"]))


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


def test_bad_seeds_are_refused_naming_seed():
    sample, ctx = _scene()
    image, lanes = sample["image"], sample["lanes"]
    for seed in (-1, None, 1.5, "3", True, np.int64(-2)):
        with pytest.raises(ValueError, match=r"^seed must be an integer >= 0, got "):
            apply_illusion(image, lanes, "rail_shadow", 3, seed=seed, context=ctx)
        with pytest.raises(ValueError, match=r"^seed must be an integer >= 0, got "):
            ILLUSIONS["rail_shadow"](image, ctx, 3, seed)
        with pytest.raises(ValueError, match=r"^seed must be an integer >= 0, got "):
            apply_illusions(image, lanes, [("rail_shadow", 3)], seed=seed, context=ctx)
    assert np.array_equal(apply_illusion(image, lanes, "rail_shadow", 3, seed=np.int64(7), context=ctx),
                          apply_illusion(image, lanes, "rail_shadow", 3, seed=7, context=ctx))


@pytest.mark.parametrize("combo, message", [
    (["rail_shadow", "vehicle"], "combo[0] must be a (name, severity) pair like ('rail_shadow', 3), got 'rail_shadow'"),
    ("rail_shadow", "combo must be a non-empty list of (name, severity) pairs, e.g. [('rail_shadow', 3), "
                    "('vehicle', 2)]; got 'rail_shadow'"),
    ({"rail_shadow": 3}, "combo must be a non-empty list of (name, severity) pairs"),
    ([], "combo must be a non-empty list of (name, severity) pairs"),
    ([("rail_shadow", 3), ("vehicle", 2, 1)], "combo[1] must be a (name, severity) pair"),
    ([("rail_shadow", 3), ("puddle", 2)], "combo[1]: unknown illusion 'puddle'"),
    ([("rail_shadow", 9)], "combo[0]: severity must be an integer from 1 (subtle) to 5 (severe), got 9"),
])
def test_bad_combos_name_the_entry(combo, message):
    sample, ctx = _scene()
    with pytest.raises(ValueError) as caught:
        apply_illusions(sample["image"], sample["lanes"], combo, context=ctx)
    assert message in str(caught.value)


@pytest.mark.parametrize("kwargs, message", [
    (dict(names=[]), "names must be a non-empty list of illusion names"),
    (dict(names=[3]), "names[0] must be an illusion name (a string), got 3"),
    (dict(severities=()), "severities must be a non-empty list of severities 1..5"),
    (dict(severities=(3, 7)), "severities[1]: severity must be an integer from 1"),
    (dict(lane_widht=3.5), "IllusionTransform got unknown keyword(s) 'lane_widht'; expected names, severities, strict, "
                           "p, or the ground-plane keywords of context_from_lanes: lane_width, camera_height"),
])
def test_illusion_transform_constructor_refuses_bad_arguments(kwargs, message):
    with pytest.raises(ValueError) as caught:
        IllusionTransform(**kwargs)
    assert message in str(caught.value)


def test_illusion_transform_accepts_one_name_and_one_severity():
    t = IllusionTransform(names="rail_shadow", severities=3, lane_width=3.5)
    assert (t.names, t.severities, t.recover_kwargs) == (["rail_shadow"], (3,), {"lane_width": 3.5})


@pytest.mark.parametrize("label_fields, got", [(None, "label_fields=[]"), (["a", "b"], "label_fields=['a', 'b']")])
def test_illusion_transform_needs_exactly_one_lane_label_field(label_fields, got):
    sample, _ = _scene()
    points = np.concatenate(sample["lanes"])
    ids = np.concatenate([np.full(len(lane), i) for i, lane in enumerate(sample["lanes"])])
    pipeline = A.Compose([IllusionTransform(names=["fence_shadow"], severities=(5,), p=1.0)],
                         keypoint_params=A.KeypointParams(format="xy", label_fields=label_fields))
    labels = {name: ids for name in label_fields or []}
    with pytest.raises(ValueError) as caught:
        pipeline(image=sample["image"], keypoints=points, **labels)
    assert str(caught.value).startswith("IllusionTransform needs the lanes as keypoints labelled by lane index")
    assert "keypoint_params=A.KeypointParams(format='xy', label_fields=['lane_ids'])" in str(caught.value)
    assert str(caught.value).endswith(f"got KeypointParams with {got}")
    with pytest.raises(ValueError, match="got no KeypointParams"):
        IllusionTransform(p=1.0)(image=sample["image"], keypoints=np.c_[points, ids])
