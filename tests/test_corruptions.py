"""The 11 non-illusion corruptions: shapes, determinism per seed, growth with severity, input checks."""

from __future__ import annotations

import random
import threading
from itertools import pairwise
from types import MappingProxyType

import numpy as np
import pytest

from lanevil_train.corruptions import (
    CORRUPTION_CATEGORIES,
    CORRUPTION_NAMES,
    CORRUPTIONS,
    Corruption,
    get_corruption,
)
from lanevil_train.sim import render_scene, sample_scene_params

RANDOM = {"snow", "rain", "fog", "motion_blur", "gaussian_noise", "iso_noise"}
SIZES = [(90, 160), (180, 320)]


@pytest.fixture(scope="module", params=SIZES, ids=lambda s: f"{s[0]}x{s[1]}")
def road(request) -> np.ndarray:
    height, width = request.param
    return render_scene(3, sample_scene_params(3), width=width, height=height)["image"]


def mad(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a.astype(np.float64) - b.astype(np.float64)).mean())


def test_names_and_categories():
    assert CORRUPTION_NAMES == ("snow", "rain", "fog", "gaussian_blur", "motion_blur", "gaussian_noise",
                                "iso_noise", "brightness", "contrast", "jpeg", "pixelate")
    assert list(CORRUPTION_CATEGORIES) == ["weather", "blur", "noise", "digital"]
    assert isinstance(CORRUPTIONS, MappingProxyType) and tuple(CORRUPTIONS) == CORRUPTION_NAMES
    assert CORRUPTIONS["iso_noise"] == Corruption("iso_noise", "noise")
    assert {c.category for c in CORRUPTIONS.values() if c.name in ("snow", "rain", "fog")} == {"weather"}
    assert get_corruption("jpeg") is CORRUPTIONS["jpeg"]


def test_every_corruption_and_severity_changes_the_image(road):
    clean = road.copy()
    for name, corruption in CORRUPTIONS.items():
        for severity in range(1, 6):
            out = corruption(road, None, severity, 0)
            assert out.dtype == np.uint8 and out.shape == road.shape, (name, severity)
            assert mad(out, road) > 1.0, (name, severity)
    np.testing.assert_array_equal(road, clean)  # the input is never modified


def test_same_seed_same_bytes_and_random_ones_vary_with_seed(road):
    np_state, py_state = np.random.get_state(), random.getstate()
    for name, corruption in CORRUPTIONS.items():
        a = corruption(road, severity=3, seed=1)
        b = corruption(road, severity=3, seed=2)
        again = corruption(road, severity=3, seed=1)  # after another seed: the cached transform keeps no state
        np.testing.assert_array_equal(a, again, err_msg=name)
        assert (not np.array_equal(a, b)) == (name in RANDOM) == corruption.random, name
    assert np.array_equal(np_state[1], np.random.get_state()[1]) and py_state == random.getstate()


def test_wrapper_equals_the_seeded_albumentations_transform(road):
    for name, corruption in CORRUPTIONS.items():
        transform = corruption.transform(4)
        assert transform is corruption.transform(4)  # built once, reused
        transform.set_random_seed(5)
        direct = transform(image=road)["image"]
        np.testing.assert_array_equal(corruption(road, None, 4, 5), direct, err_msg=name)


def test_distortion_strictly_grows_with_severity(road):
    for name, corruption in CORRUPTIONS.items():
        distortion = [mad(corruption(road, None, s, 0), road) for s in range(1, 6)]
        assert all(lo < hi for lo, hi in pairwise(distortion)), (name, np.round(distortion, 2))


def test_ladders_move_the_documented_way(road):
    quality = [CORRUPTIONS["jpeg"].transform(s).quality_range for s in range(1, 6)]
    assert quality == [(25, 25), (18, 18), (15, 15), (10, 10), (7, 7)]
    scales = [CORRUPTIONS["pixelate"].transform(s).scale_range[0] for s in range(1, 6)]
    assert scales == sorted(scales, reverse=True) and scales[0] == 0.5
    brighter = [CORRUPTIONS["brightness"](road, severity=s).mean() for s in range(1, 6)]
    assert all(lo < hi for lo, hi in pairwise(brighter)) and brighter[0] > road.mean() + 20
    flat = [CORRUPTIONS["contrast"](road, severity=s) for s in (1, 5)]
    assert flat[0].std() < 0.45 * road.std() and flat[1].std() < 0.1 * road.std()
    assert abs(flat[1].mean() - road.mean()) < 3  # contrast pulls towards the mean, it does not darken


def test_rain_draws_streaks_on_a_tiny_image():
    image = render_scene(1, sample_scene_params(1), width=160, height=64)["image"]
    out = CORRUPTIONS["rain"](image, None, 1, 0)
    brighter = (out.astype(int) - image > 20).any(axis=2).sum()  # darkening alone cannot brighten a pixel
    assert 10 < brighter < 0.5 * image.shape[0] * image.shape[1]


def test_threads_get_their_own_transforms_and_the_same_bytes(road):
    corruption = CORRUPTIONS["gaussian_noise"]
    results, transforms = {}, {}

    def work(key):
        transforms[key] = corruption.transform(2)
        results[key] = corruption(road, severity=2, seed=9)

    threads = [threading.Thread(target=work, args=(k,)) for k in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert transforms[0] is not transforms[1]
    np.testing.assert_array_equal(results[0], results[1])
    np.testing.assert_array_equal(results[0], corruption(road, severity=2, seed=9))


@pytest.mark.parametrize("bad", [0, 6, 2.0, True, "3", None])
def test_bad_severity(bad):
    image = np.zeros((64, 160, 3), np.uint8)
    with pytest.raises(ValueError, match="severity"):
        CORRUPTIONS["fog"](image, severity=bad)
    with pytest.raises(ValueError, match="severity"):
        CORRUPTIONS["fog"].transform(bad)


@pytest.mark.parametrize("bad", [-1, 1.5, "0", None])
def test_bad_seed(bad):
    with pytest.raises(ValueError, match="seed"):
        CORRUPTIONS["rain"](np.zeros((64, 160, 3), np.uint8), severity=1, seed=bad)


@pytest.mark.parametrize("bad", [np.zeros((64, 160, 3), np.float32), np.zeros((64, 160), np.uint8),
                                 np.zeros((64, 160, 4), np.uint8), np.zeros((4, 160, 3), np.uint8), [[0, 0, 0]]])
def test_bad_image(bad):
    with pytest.raises(ValueError, match="image"):
        CORRUPTIONS["jpeg"](bad, severity=1)


def test_unknown_name_lists_the_known_ones():
    with pytest.raises(ValueError, match="corruption name 'hail'.*snow, rain, fog"):
        get_corruption("hail")
    with pytest.raises(ValueError, match="corruption name"):
        get_corruption(None)
