"""Camera: projection <-> ground back-projection round trips; intrinsics scale with image size."""

import numpy as np
import pytest

from lanevil_train.lanes import lane_x_at, scale_lanes
from lanevil_train.sim import Camera, SceneParams, build_scene, render_scene


def test_default_intrinsics():
    cam = Camera()
    assert (cam.width, cam.height) == (1280, 720)
    assert cam.fx == pytest.approx(640.0)  # 90 deg HFOV
    assert cam.cx == pytest.approx(639.5) and cam.cy == pytest.approx(359.5)
    small = cam.scaled(640, 360)
    assert small.fx == pytest.approx(cam.fx / 2)
    # a point straight ahead at camera height is the principal point when pitch = 0
    flat = Camera(pitch_deg=0.0)
    u, v = flat.project(np.array([[0.0, 1.5, 30.0]]))[0]
    assert u == pytest.approx(639.5) and v == pytest.approx(359.5)
    # a ground point 1.5 m below at 1.5 m ahead is 45 deg down: fy pixels below the centre
    u, v = flat.project(np.array([[0.0, 0.0, 1.5]]))[0]
    assert v == pytest.approx(359.5 + 640.0)


@pytest.mark.parametrize("road", ["straight", "uphill", "downhill", "s_curve"])
def test_project_then_backproject_round_trip(road):
    scene = build_scene(0, SceneParams(road=road, pitch_deg=3.0, yaw_deg=2.0, grade=0.1), 640, 360)
    z = np.linspace(3.0, 60.0, 25)
    for d in (-5.0, 0.0, 4.0):
        pts = scene.road.world_point(d, z)
        pix = scene.camera.project(pts)
        back = scene.ground_hit(pix[:, 0], pix[:, 1])
        # beyond a downhill crest the ray meets the crest first: never farther than the point
        assert np.all(back[:, 2] <= pts[:, 2] + 1e-6)
        vis = z <= 30.0
        np.testing.assert_allclose(back[vis], pts[vis], atol=1e-6 * 60, rtol=1e-6)
        if road != "downhill":
            np.testing.assert_allclose(back, pts, atol=1e-6 * 60, rtol=1e-6)


def test_backproject_then_project_round_trip():
    cam = Camera(width=320, height=180, pitch_deg=4.0, yaw_deg=-3.0)
    u, v = np.meshgrid(np.linspace(0, 319, 9), np.linspace(120, 179, 7))
    pts = cam.ground_intersect(u, v)
    assert np.all(np.isfinite(pts)) and np.allclose(pts[..., 1], 0.0)
    np.testing.assert_allclose(cam.project(pts), np.stack([u, v], -1), atol=1e-7)
    # above the horizon the ray misses
    assert np.all(np.isnan(cam.ground_intersect(np.array([160.0]), np.array([0.0]))))


def test_lanes_scale_with_image_size():
    p = SceneParams(road="left_curve", num_lanes=4, curvature=1 / 200)
    big = render_scene(3, p, 1280, 720)
    small = render_scene(3, p, 640, 360)
    assert len(big["lanes"]) == len(small["lanes"]) == 5
    rows = np.arange(170.0, 359.0, 1.0)
    for lb, ls in zip(big["lanes"], small["lanes"]):
        # exact relation between pixel-index coordinates: x_small = (x_big + 0.5) / 2 - 0.5
        xs = lane_x_at(ls, rows)
        xb = lane_x_at(lb, 2 * rows + 0.5)
        ok = (xs >= 0) & (xb >= 0)
        assert ok.sum() > 20
        np.testing.assert_allclose(xs[ok], (xb[ok] + 0.5) / 2 - 0.5, atol=0.15)
        # plain scaling by 0.5 stays within 1 px of the small lane (distance to its polyline)
        scaled = scale_lanes([lb], 0.5, 0.5)[0]
        ys = np.arange(ls[:, 1].min(), ls[:, 1].max(), 0.05)
        dense = np.stack([lane_x_at(ls, ys), ys], axis=1)
        inside = (scaled[:, 1] >= ls[:, 1].min() + 1) & (scaled[:, 1] <= ls[:, 1].max() - 1)
        dist = np.min(np.linalg.norm(scaled[inside, None, :] - dense[None], axis=2), axis=1)
        assert inside.sum() > 20 and dist.max() < 1.0
