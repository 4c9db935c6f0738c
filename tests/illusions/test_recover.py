"""recover.py: the context recovered from a simulated camera's lanes matches that camera."""

import math

import numpy as np
import pytest

from lanevil_train.illusions import apply_illusion, apply_illusions
from lanevil_train.illusions.context import IllusionContext, context_from_scene
from lanevil_train.illusions.recover import (
    LANE_X_MARGIN_FRAC,
    LANE_Y_MARGIN_FRAC,
    GroundPlaneError,
    context_from_lanes,
    fallback_context,
)
from lanevil_train.lanes import TUSIMPLE_H_SAMPLES, lanes_to_rows, rows_to_lane
from lanevil_train.sim import SceneParams, build_scene

# (pitch_deg, yaw_deg, camera_height, lane_width, num_lanes, lateral_offset)
CAMERAS = [
    (2.0, 0.0, 1.5, 3.5, 3, 0.0),
    (5.0, 3.0, 1.2, 3.0, 4, 0.4),
    (0.5, -4.0, 2.5, 4.0, 2, -0.3),
    (8.0, 10.0, 3.0, 3.6, 5, 0.0),
    (-2.0, 1.5, 1.8, 3.75, 3, 0.8),
]


def _scene(pitch, yaw, hcam, lw, nl, lo, width=1280, height=720):
    params = SceneParams(road="straight", pitch_deg=pitch, yaw_deg=yaw, camera_height=hcam,
                         lane_width=lw, num_lanes=nl, lateral_offset=lo)
    return build_scene(3, params, width, height)


def _tusimple_lanes(scene):
    """GT lanes as a TuSimple annotator would give them: x on the 10-px rows, rounded to integers."""
    lanes, _, offsets = scene.lanes()
    rows = np.round(lanes_to_rows(lanes, TUSIMPLE_H_SAMPLES))
    rows[rows < 0] = -2.0
    rows[rows >= scene.camera.width] = -2.0
    return [rows_to_lane(r, TUSIMPLE_H_SAMPLES) for r in rows], offsets


@pytest.mark.parametrize("cam", CAMERAS)
def test_recovers_simulated_camera_from_rounded_tusimple_rows(cam):
    pitch, yaw, hcam, lw, _, _ = cam
    scene = _scene(*cam)
    lanes, true_offsets = _tusimple_lanes(scene)
    ctx = context_from_lanes(lanes, (720, 1280), lane_width=lw)
    assert isinstance(ctx, IllusionContext)
    assert abs(ctx.camera.pitch_deg - pitch) < 0.3
    assert abs(ctx.camera.yaw_deg - yaw) < 0.3
    assert abs(ctx.camera.height_m - hcam) < 0.05 * hcam
    # offsets relative to the road centre (midpoint of the outermost lanes), as in the simulator
    true = np.asarray(true_offsets)
    assert len(ctx.lane_offsets) == len(true)
    np.testing.assert_allclose(ctx.lane_offsets, true, atol=0.05 * lw)
    assert [b.d for b in ctx.road.boundaries] == list(ctx.lane_offsets)
    # the camera sits where it does in the scene: same road centre x (within 5 % of a lane)
    assert abs(ctx.road.x0 - scene.road.x0) < 0.05 * lw


@pytest.mark.parametrize("cam", CAMERAS[:3])
def test_near_field_projection_matches_true_camera(cam):
    scene = _scene(*cam)
    lanes, _ = _tusimple_lanes(scene)
    ctx = context_from_lanes(lanes, (720, 1280), lane_width=cam[3])
    true_ctx = context_from_scene(scene)
    d, z = np.meshgrid(np.linspace(-4.0, 4.0, 9), np.linspace(6.0, 30.0, 9))
    got = ctx.camera.project(ctx.road.world_point(d, z))
    want = true_ctx.camera.project(true_ctx.road.world_point(d, z))
    inside = np.all((want >= 0) & (want < [1280, 720]), axis=-1)
    assert inside.sum() > 20
    err = np.linalg.norm(got - want, axis=-1)[inside]
    assert err.max() < 2.0


def test_exact_lanes_give_exact_camera():
    scene = _scene(5.0, 3.0, 1.2, 3.0, 4, 0.4)
    lanes, _, offsets = scene.lanes()
    ctx = context_from_lanes(lanes, (720, 1280), lane_width=3.0)
    assert ctx.camera.pitch_deg == pytest.approx(5.0, abs=1e-6)
    assert ctx.camera.yaw_deg == pytest.approx(3.0, abs=1e-6)
    assert ctx.camera.height_m == pytest.approx(1.2, abs=1e-6)
    np.testing.assert_allclose(ctx.lane_offsets, offsets, atol=1e-6)


def test_camera_outside_the_annotated_lanes_keeps_its_lane_on_the_road():
    # the ego lane's right line is not annotated (an unmarked road edge): the recovered asphalt must
    # still reach past the camera, so illusions clipped to the road show in the camera's own lane
    scene = _scene(2.0, 0.0, 1.5, 3.5, 3, 0.0)
    lanes, _, offsets = scene.lanes()
    ctx = context_from_lanes(lanes[:2], (720, 1280), lane_width=3.5)  # the two lines left of the camera
    d_cam = float(ctx.road.lateral(0.0, 0.0))
    assert d_cam > max(ctx.lane_offsets)
    assert ctx.road.right_edge > d_cam + 1.5
    assert [b.d for b in ctx.road.boundaries if b.marking != "none"] == list(ctx.lane_offsets)
    assert len(ctx.lane_offsets) == 2


def test_small_image_and_hfov():
    params = SceneParams(road="straight", pitch_deg=3.0, yaw_deg=-2.0, camera_height=1.6, lane_width=3.5,
                         hfov_deg=60.0, num_lanes=3)
    scene = build_scene(0, params, 320, 180)
    lanes, _, offsets = scene.lanes()
    lanes = [np.round(lane) for lane in lanes]
    ctx = context_from_lanes(lanes, (180, 320), lane_width=3.5, hfov_deg=60.0)
    assert ctx.image_size == (180, 320)
    assert abs(ctx.camera.pitch_deg - 3.0) < 0.3 and abs(ctx.camera.yaw_deg + 2.0) < 0.3
    np.testing.assert_allclose(ctx.lane_offsets, offsets, atol=0.05 * 3.5)


def test_lane_width_none_uses_camera_height():
    scene = _scene(2.0, 0.0, 1.5, 3.5, 3, 0.0)
    lanes, _, offsets = scene.lanes()
    ctx = context_from_lanes(lanes, (720, 1280), lane_width=None, camera_height=3.0)
    assert ctx.camera.height_m == 3.0
    # twice the height => everything twice as wide
    np.testing.assert_allclose(ctx.lane_offsets, 2.0 * np.asarray(offsets), atol=1e-6)
    assert ctx.lane_width == pytest.approx(7.0, abs=1e-6)
    # and with a lane width given, the lanes are that far apart whatever camera_height says
    ctx2 = context_from_lanes(lanes, (720, 1280), lane_width=3.2, camera_height=3.0)
    assert ctx2.lane_width == pytest.approx(3.2, abs=1e-9)
    assert ctx2.camera.height_m == pytest.approx(1.5 * 3.2 / 3.5, abs=1e-6)


def test_short_lanes_are_ignored_but_two_good_ones_suffice():
    scene = _scene(2.0, 1.0, 1.5, 3.5, 3, 0.0)
    lanes, _, offsets = scene.lanes()
    stub = lanes[1][:3]  # three points: unusable
    # the adjacent recovered lanes are two lanes apart: 7 m, re-centred on their midpoint
    ctx = context_from_lanes([lanes[0], stub, lanes[2]], (720, 1280), lane_width=7.0)
    assert len(ctx.lane_offsets) == 2
    assert abs(ctx.camera.yaw_deg - 1.0) < 1e-6
    assert ctx.camera.height_m == pytest.approx(1.5, abs=1e-6)
    np.testing.assert_allclose(ctx.lane_offsets, [-3.5, 3.5], atol=1e-6)
    assert offsets[2] - offsets[0] == pytest.approx(7.0)


def test_sun_night_wet_passed_through():
    scene = _scene(2.0, 0.0, 1.5, 3.5, 3, 0.0)
    lanes, _, _ = scene.lanes()
    day = context_from_lanes(lanes, (720, 1280))
    assert day.sun_direction[1] == pytest.approx(math.sin(math.radians(60.0)))
    assert np.linalg.norm(day.sun_direction) == pytest.approx(1.0)
    night = context_from_lanes(lanes, (720, 1280), night=True, wet=0.7)
    assert night.night and night.wet == 0.7 and night.sun_direction[1] < 0
    custom = context_from_lanes(lanes, (720, 1280), sun_direction=np.array([0.0, 2.0, 0.0]))
    np.testing.assert_allclose(custom.sun_direction, [0.0, 1.0, 0.0])
    with pytest.raises(ValueError, match="sun_direction"):
        context_from_lanes(lanes, (720, 1280), sun_direction=np.zeros(3))
    with pytest.raises(ValueError, match="wet"):
        context_from_lanes(lanes, (720, 1280), wet=2.0)


def test_errors_name_the_problem_and_suggest_fallback():
    scene = _scene(2.0, 0.0, 1.5, 3.5, 3, 0.0)
    lanes, _, _ = scene.lanes()
    with pytest.raises(GroundPlaneError, match="at least 2 usable lanes.*got 0.*fallback_context"):
        context_from_lanes([], (720, 1280))
    with pytest.raises(GroundPlaneError, match="got 1 of 1.*fallback_context"):
        context_from_lanes([lanes[0]], (720, 1280))
    ys = np.arange(710.0, 400.0, -10.0)
    parallel = [np.stack([np.full_like(ys, x), ys], axis=1) for x in (300.0, 700.0)]
    with pytest.raises(GroundPlaneError, match="parallel.*fallback_context"):
        context_from_lanes(parallel, (720, 1280))
    # lanes converging downwards: they meet below the lanes
    down = [np.stack([600.0 - (700.0 - ys) * s, ys], axis=1) for s in (0.5, -0.5)]
    with pytest.raises(GroundPlaneError, match="not above the lanes"):
        context_from_lanes(down, (720, 1280))
    # lanes meeting far above the image: pitch beyond 30 degrees
    steep = [np.stack([640.0 + (ys + 2000.0) * s, ys], axis=1) for s in (-0.2, 0.2)]
    with pytest.raises(GroundPlaneError, match="pitch"):
        context_from_lanes(steep, (720, 1280))
    assert issubclass(GroundPlaneError, ValueError)
    with pytest.raises(ValueError, match=r"lanes\[1\]"):
        context_from_lanes([lanes[0], np.zeros((4, 3))], (720, 1280))
    with pytest.raises(ValueError, match="camera_height"):
        context_from_lanes(lanes, (720, 1280), lane_width=None, camera_height=0.05)
    with pytest.raises(ValueError, match="image_size"):
        context_from_lanes(lanes, (720,))


def test_fallback_context_is_usable():
    ctx = fallback_context((720, 1280), camera_height=1.6, pitch_deg=3.0, lane_width=3.5, num_lanes=4)
    assert ctx.image_size == (720, 1280)
    np.testing.assert_allclose(ctx.lane_offsets, [-5.25, -1.75, 1.75, 5.25])
    assert ctx.lane_width == pytest.approx(3.5)
    # the camera (x = 0) is in the middle of the ego lane (between lines 1 and 2)
    assert ctx.road.lateral(0.0, 10.0) == pytest.approx(0.0)
    # ego-lane lines project symmetrically and below the horizon, converging with distance
    near = ctx.camera.project(ctx.road.world_point(np.array([-1.75, 1.75]), np.array([10.0, 10.0])))
    far = ctx.camera.project(ctx.road.world_point(np.array([-1.75, 1.75]), np.array([40.0, 40.0])))
    assert near[0, 0] + near[1, 0] == pytest.approx(2 * ctx.camera.cx)
    assert near[1, 0] - near[0, 0] > far[1, 0] - far[0, 0] > 0
    horizon = ctx.camera.cy - ctx.camera.fy * math.tan(math.radians(3.0))
    assert near[0, 1] > far[0, 1] > horizon
    # the lanes it implies can be recovered again (round trip)
    three = fallback_context((720, 1280), num_lanes=3, lane_width=3.0)
    np.testing.assert_allclose(three.lane_offsets, [-3.0, 0.0, 3.0])
    assert three.road.lateral(0.0, 5.0) == pytest.approx(1.5)  # camera mid-lane, right of the centre line
    zs = np.linspace(5.0, 60.0, 40)
    lanes = [ctx.camera.project(ctx.road.world_point(np.full_like(zs, d), zs)) for d in ctx.lane_offsets]
    back = context_from_lanes(lanes, (720, 1280), lane_width=3.5)
    assert back.camera.pitch_deg == pytest.approx(3.0, abs=1e-6)
    assert back.camera.height_m == pytest.approx(1.6, abs=1e-6)
    with pytest.raises(ValueError, match="num_lanes"):
        fallback_context((720, 1280), num_lanes=1)


@pytest.mark.parametrize("road", ["left_curve", "uphill", "downhill"])
def test_near_band_fit_copes_with_curves_and_hills(road):
    # the far ends bend away (a 300 m curve; a 6 % grade from 20 m): the near band is still a flat road
    params = SceneParams(road=road, pitch_deg=2.5, camera_height=1.5, lane_width=3.5, num_lanes=3)
    scene = build_scene(3, params, 1280, 720)
    lanes, offsets = _tusimple_lanes(scene)
    ctx = context_from_lanes(lanes, (720, 1280), lane_width=3.5)
    assert abs(ctx.camera.pitch_deg - 2.5) < 0.3
    assert abs(ctx.camera.height_m - 1.5) < 0.05 * 1.5
    np.testing.assert_allclose(ctx.lane_offsets, offsets, atol=0.05 * 3.5)
    if road != "left_curve":
        assert abs(ctx.camera.yaw_deg) < 0.3
    else:  # the near road heading has turned left a little: the camera looks right of it
        assert 0.0 < ctx.camera.yaw_deg < 2.0


def test_noisy_annotations_stay_close():
    rng = np.random.default_rng(0)
    scene = _scene(3.0, 2.0, 1.5, 3.5, 4, 0.2)
    lanes, offsets = _tusimple_lanes(scene)
    noisy = [lane + np.stack([rng.normal(0.0, 1.5, len(lane)), np.zeros(len(lane))], axis=1) for lane in lanes]
    ctx = context_from_lanes(noisy, (720, 1280), lane_width=3.5)
    assert abs(ctx.camera.pitch_deg - 3.0) < 0.3 and abs(ctx.camera.yaw_deg - 2.0) < 0.3
    np.testing.assert_allclose(ctx.lane_offsets, offsets, atol=0.05 * 3.5)


# ----------------------------------------------------------------------------- lanes outside the image
EXPECTED_PIXELS = ("expected (x, y) pixels of this image: at least one point in x 0..1280, y 0..720 and every point "
                   "within x -1280..2560, y -14.4..734.4. Are the lanes for another image size, or (y, x) pairs?")


def _line(slope, ys=np.arange(710.0, 399.0, -10.0)):
    """A straight lane x = 640 + slope * (y - 300): lines of different slopes meet at (640, 300)."""
    return np.stack([640.0 + slope * (ys - 300.0), ys], axis=1)


def _three_lanes():
    """Three lanes of 32 points (rows 710..400) inside a 1280x720 image; the first spans x 148..520."""
    return [_line(s) for s in (-1.2, 0.1, 1.2)]


def _raises_everywhere(lanes, message):
    """context_from_lanes, apply_illusion and apply_illusions all raise GroundPlaneError(message)."""
    image = np.full((720, 1280, 3), 90, np.uint8)
    calls = [lambda: context_from_lanes(lanes, (720, 1280)),
             lambda: apply_illusion(image, lanes, "vehicle", 3),
             lambda: apply_illusion(image, lanes, "rail_shadow", 5),
             lambda: apply_illusions(image, lanes, [("fence_shadow", 2), ("vehicle", 2)])]
    for call in calls:
        with pytest.raises(GroundPlaneError) as err:
            call()
        assert str(err.value) == message


def test_the_lanes_of_these_tests_are_fine():
    ctx = context_from_lanes(_three_lanes(), (720, 1280))
    assert ctx.camera.pitch_deg == pytest.approx(math.degrees(math.atan2(ctx.camera.cy - 300.0, ctx.camera.fy)))
    assert len(ctx.lane_offsets) == 3


def test_lanes_all_below_the_image_are_rejected():
    lanes = [lane + [0.0, 720.0] for lane in _three_lanes()]  # rows 1120..1430 of a 720-row image
    _raises_everywhere(lanes, "lanes[0]: none of its 32 points lies in the image (1280 wide, 720 high): they span "
                              "x 148.0..520.0, y 1120.0..1430.0; " + EXPECTED_PIXELS)


def test_lanes_all_right_of_the_image_are_rejected():
    lanes = [lane + [1280.0, 0.0] for lane in _three_lanes()]
    _raises_everywhere(lanes, "lanes[0]: none of its 32 points lies in the image (1280 wide, 720 high): they span "
                              "x 1428.0..1800.0, y 400.0..710.0; " + EXPECTED_PIXELS)


def test_one_lane_outside_is_named_when_the_others_are_fine():
    lanes = _three_lanes()
    lanes[2] = lanes[2] * 2.0  # lanes[2] in the pixels of a twice larger image: wholly outside
    _raises_everywhere(lanes, "lanes[2]: none of its 32 points lies in the image (1280 wide, 720 high): they span "
                              "x 1520.0..2264.0, y 800.0..1420.0; " + EXPECTED_PIXELS)
    lanes = _three_lanes()
    lanes[1] = lanes[1] * [1.0, 1.5]  # starts in the image, ends 700 rows below it
    _raises_everywhere(lanes, "lanes[1]: 23 of its 32 points lie too far outside the image (1280 wide, 720 high): "
                              "those span x 659.0..681.0, y 735.0..1065.0; " + EXPECTED_PIXELS)


def test_lanes_slightly_outside_within_the_margins_are_accepted():
    assert (LANE_X_MARGIN_FRAC, LANE_Y_MARGIN_FRAC) == (1.0, 0.02)
    reference = context_from_lanes(_three_lanes(), (720, 1280))
    # CULane-like: the left lane's spline runs on to the bottom row (y = 720, the edge), x there -200
    lanes = _three_lanes()
    lanes[0] = _line(-2.0, np.arange(720.0, 399.0, -10.0))
    assert lanes[0][0].tolist() == [-200.0, 720.0]
    ctx = context_from_lanes(lanes, (720, 1280))
    assert ctx.camera.pitch_deg == pytest.approx(reference.camera.pitch_deg, abs=1e-9)
    # right at the margins: x one image width out, y 2 % of the height below
    lanes = _three_lanes()
    lanes[2] = np.concatenate([[[2560.0, 734.4]], lanes[2]])
    lanes[0] = np.concatenate([[[-1280.0, 720.0]], lanes[0]])
    assert isinstance(context_from_lanes(lanes, (720, 1280)), IllusionContext)
    image = np.full((720, 1280, 3), 90, np.uint8)
    assert apply_illusion(image, lanes, "vehicle", 3).shape == image.shape
    # and just beyond them
    lanes[2][0, 1] = 734.5
    with pytest.raises(GroundPlaneError, match=r"^lanes\[2\]: 1 of its 33 points lie too far outside the image "
                                               r"\(1280 wide, 720 high\): those span x 2560.0..2560.0, y 734.5..734.5"):
        context_from_lanes(lanes, (720, 1280))
    # TuSimple's x = -2 rows are "no point", not points left of the image
    lanes = _three_lanes()
    lanes[1][:5, 0] = -2.0
    assert isinstance(context_from_lanes(lanes, (720, 1280)), IllusionContext)


@pytest.mark.parametrize("value, shown", [(np.nan, "nan"), (np.inf, "inf"), (-np.inf, "-inf")])
def test_non_finite_lane_coordinates_name_the_lane(value, shown):
    lanes = _three_lanes()
    lanes[1][3, 0] = value
    message = (f"lanes[1]: point 3 is ({shown}, 680.0); expected finite (x, y) pixel coordinates (leave a row "
               f"without a point out, or give x = -2 as TuSimple does)")
    with pytest.raises(ValueError) as err:
        context_from_lanes(lanes, (720, 1280))
    assert str(err.value) == message
    with pytest.raises(ValueError) as err:
        apply_illusion(np.full((720, 1280, 3), 90, np.uint8), lanes, "vehicle", 3)
    assert str(err.value) == message
    lanes = _three_lanes()
    lanes[2][0, 1] = value
    with pytest.raises(ValueError, match=rf"^lanes\[2\]: point 0 is \(1132.0, {shown}\); expected finite"):
        context_from_lanes(lanes, (720, 1280))
