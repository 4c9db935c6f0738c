"""Collisions: the car's rectangle against obstacle rectangles on constructed traces (times computed by hand),
and the obstacles a standing illusion draws into a real simulated scene, against the illusion's own layout."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lanevil_train.closed_loop.collisions import (
    FRONT_OVERHANG_M,
    REAR_OVERHANG_M,
    Obstacle,
    car_corners,
    collision,
    obstacles,
)
from lanevil_train.closed_loop.episode import case_scene, ego_lane, illusion_region
from lanevil_train.closed_loop.run_scores import entry_time
from lanevil_train.illusions import traffic
from lanevil_train.illusions.context import context_from_scene
from lanevil_train.illusions.registry import get_illusion

FRONT = 2.7 + FRONT_OVERHANG_M  # rear axle to front bumper: 3.6 m


def _straight(n, d=0.0, t0=0.0, s0=0.0, speed=20.0, dt=0.1, heading=0.0):
    return [{"t": t0 + i * dt, "s": s0 + i * dt * speed, "d": d, "deviation": d, "heading": heading}
            for i in range(n)]


def test_the_car_footprint_runs_from_behind_the_rear_axle_to_the_front_bumper():
    corners = car_corners(10.0, 1.0, 0.0)
    assert corners[:, 0].min() == pytest.approx(10.0 - REAR_OVERHANG_M) and corners[:, 0].max() == pytest.approx(13.6)
    assert corners[:, 1].min() == pytest.approx(0.1) and corners[:, 1].max() == pytest.approx(1.9)


def test_a_car_driving_straight_into_a_box_collides_when_its_front_reaches_it():
    box = Obstacle("vehicle", s_near=30.0, s_far=34.5, d_left=-0.5, d_right=0.5)
    trace = _straight(30, t0=2.0)
    # front at s + 3.6 reaches 30 m when s = 26.4 m: 1.32 s after the start at 20 m/s
    entry = entry_time(trace, 30.0)  # the rear axle reaches the box's near end at 1.5 s
    out = collision(trace, box, entry_s=entry)
    assert out["collision"] and out["collision_t"] == pytest.approx(3.32, abs=1e-4)
    assert out["time_to_collision_s"] == pytest.approx(1.32, abs=1e-4)
    assert out["collision_after_entry_s"] == pytest.approx(-0.18, abs=1e-4)
    assert out["obstacle"]["s_near"] == 30.0
    assert collision(trace, box)["collision_after_entry_s"] is None


def test_a_car_passing_0_2m_beside_a_box_does_not_collide_and_0_1m_into_it_does():
    box = Obstacle("vehicle", s_near=30.0, s_far=34.5, d_left=1.1, d_right=2.0)
    assert collision(_straight(40), box)["collision"] is False  # right side at 0.9 m, 0.2 m from the box
    hit = collision(_straight(40, d=0.3), box)  # right side at 1.2 m
    assert hit["collision"] and hit["collision_t"] == pytest.approx(26.4 / 20.0, abs=1e-4)


def test_a_thin_object_between_two_steps_is_hit_when_the_front_reaches_it_not_at_the_next_step():
    thin = Obstacle("pedestrian", s_near=30.0, s_far=30.3, d_left=-0.3, d_right=0.3)
    out = collision(_straight(30), thin)  # steps at s = 26 and 28 m (t 1.3, 1.4 s); contact at s = 26.4 m
    assert out["collision_t"] == pytest.approx(1.32, abs=1e-4)
    # steps 6 m apart: the car spans [-1, 3.6] m then [5, 9.6] m; only the poses between them touch [4, 4.3]
    coarse = _straight(5, dt=0.3)
    between = Obstacle("pedestrian", s_near=4.0, s_far=4.3, d_left=-0.3, d_right=0.3)
    out = collision(coarse, between)
    assert out["collision"] and out["collision_t"] == pytest.approx(0.4 / 20.0, abs=1e-4)
    assert collision(coarse, between, substep_m=100.0)["collision"] is False  # steps alone tunnel through it


def test_a_car_angled_10_degrees_touches_a_box_a_straight_car_misses():
    box = Obstacle("vehicle", s_near=3.0, s_far=4.0, d_left=1.2, d_right=2.0)
    straight = [{"t": 5.0, "s": 0.0, "d": 0.0, "heading": 0.0}]
    angled = [{"t": 5.0, "s": 0.0, "d": 0.0, "heading": math.radians(10.0)}]
    # straight: right side at d = 0.9 < 1.2. Angled: front-right corner at
    # (3.6 cos 10 - 0.9 sin 10, 3.6 sin 10 + 0.9 cos 10) = (3.389, 1.511), inside the box
    corner = car_corners(0.0, 0.0, math.radians(10.0))[2]
    assert corner == pytest.approx([3.38902, 1.51146], abs=1e-5)
    assert collision(straight, box)["collision"] is False
    out = collision(angled, box)
    assert out["collision"] and out["collision_t"] == 5.0 and out["time_to_collision_s"] == 0.0
    # angled 10 degrees left, the car's front-right corner is at d = 0.9 cos 10 - 3.6 sin 10 = 0.261: no contact
    assert collision([{**angled[0], "heading": math.radians(-10.0)}], box)["collision"] is False


def test_the_first_obstacle_hit_in_time_is_reported_and_no_obstacle_is_no_collision():
    far = Obstacle("vehicle", s_near=50.0, s_far=54.5, d_left=-1.0, d_right=1.0)
    near = Obstacle("vehicle", s_near=20.0, s_far=24.5, d_left=0.5, d_right=1.5)
    out = collision(_straight(40), [far, near])
    assert out["obstacle"]["s_near"] == 20.0 and out["collision_t"] == pytest.approx(16.4 / 20.0, abs=1e-4)
    assert collision(_straight(40), None)["collision"] is False
    assert collision(_straight(40), [])["collision_t"] is None


def test_an_illusion_that_does_not_stand_on_the_road_has_no_obstacle():
    scene, _ = case_scene(1000000, (360, 640))
    assert obstacles(scene, "rail_shadow", 3, 1000000) == []
    assert obstacles(scene, "vehicle", 0, 1000000) == []  # a clean twin


def test_the_vehicle_illusion_of_case_1000000_gives_its_two_vehicles_where_its_layout_put_them():
    seed, size = 1000000, (360, 640)
    scene, clean = case_scene(seed, size)
    # the layout the illusion drew, from its parts' box corners (by hand from traffic.layout): a car on the ego
    # lane's left line (s 14.75-19.19, d 0.72-2.82) and a box truck on its right line (s 15.55-23.10, d 4.48-7.25)
    ctx = context_from_scene(scene)
    truth = []
    for part in traffic.layout("vehicle", ctx, 3, np.random.default_rng(seed)):
        origin, axes = traffic._frame(ctx, part)
        corners = np.concatenate([traffic._world_vertices(q, origin, axes) for q in part.prims])
        s, d = scene.road_coords(corners[:, 0], corners[:, 2])
        truth.append([s.min(), s.max(), d.min(), d.max()])
    assert np.round(sorted(truth), 2).tolist() == [[14.75, 19.19, 0.72, 2.82], [15.55, 23.1, 4.48, 7.25]]
    found = obstacles(scene, "vehicle", 3, seed)
    assert np.allclose([[o.s_near, o.s_far, o.d_left, o.d_right] for o in found], sorted(truth), atol=1e-9)
    # the illusion drawn with this seed is the one that changed the image there: its pixels lie over the boxes
    perturbed = get_illusion("vehicle")(clean, ctx, 3, seed)
    assert abs(found[0].s_near - illusion_region(seed, "vehicle", size)[0]) < 2.5  # the region starts at shadows
    assert not np.array_equal(perturbed, clean)
    # a car held at the ego lane's centre (3.542: its sides 2.642-4.442) meets the car (d_right 2.82) when its
    # front reaches it; the truck's left side (4.48) clears it by 4 cm
    centre = ego_lane(scene)[0]
    assert centre == pytest.approx(3.542, abs=1e-3)
    out = collision(_straight(20, d=centre, s0=5.0), found)
    assert out["collision"] and out["obstacle"] == found[0].as_dict()
    assert out["collision_t"] == pytest.approx((found[0].s_near - FRONT - 5.0) / 20.0, abs=1e-4)
    assert not collision(_straight(20, d=centre, s0=5.0), found[1])["collision"]


def test_a_guard_rail_stands_beyond_the_roads_outer_line_from_where_it_starts():
    seed = 1000000
    scene, _ = case_scene(seed, (360, 640))
    rails = obstacles(scene, "guard_rail", 3, seed)  # one rail, 0.9 m outside an edge line, from 6 m
    edges = [b.d for b in scene.road.boundaries]
    assert len(rails) == 1
    rail = rails[0]
    outside = rail.d_left - max(edges) if rail.d_left > max(edges) else min(edges) - rail.d_right
    assert outside == pytest.approx(0.9 - 0.15, abs=1e-6)  # the beam's face, 0.15 m on the road side of the posts
    assert rail.d_right - rail.d_left == pytest.approx(0.15 + 0.08)
    assert rail.s_near == pytest.approx(float(scene.road.arc_length(np.array(6.0))), abs=1e-6)
