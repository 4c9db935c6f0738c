"""Data-only defense transforms: cutout paints exactly its holes and keeps every lane point; strong HSV."""

from __future__ import annotations

import pickle

import albumentations as A
import numpy as np
import pytest

from lanevil_train.data.defenses import IMAGENET_MEAN_UINT8, LaneCutout, fill_holes, hsv_jitter
from lanevil_train.data.transforms import apply_pipeline, build_pipeline, normalize_image

H, W = 64, 160


def _scene(seed: int = 0) -> tuple[np.ndarray, list[np.ndarray]]:
    """Textured image whose pixel values avoid the fill colours, and three lanes."""
    rng = np.random.default_rng(seed)
    image = rng.integers(130, 250, size=(H, W, 3), dtype=np.uint8)  # never 0 nor the ImageNet mean
    ys = np.arange(H - 1, 3, -3.0)
    lanes = [np.stack([x0 + slope * (H - 1 - ys), ys], 1) for x0, slope in ((30.0, 0.6), (80.0, 0.0), (130.0, -0.6))]
    return image, lanes


def _holes_from(applied: list) -> np.ndarray:
    (holes,) = [params["holes"] for name, params in applied if name == "LaneCutout"]
    return holes


def test_cutout_paints_exactly_the_holes_it_reports():
    image, lanes = _scene()
    cutout = LaneCutout(num_holes=(2, 4), hole_height=(0.2, 0.4), hole_width=(0.1, 0.2), fill=0, p=1.0)
    pipe = A.Compose([cutout], save_applied_params=True, seed=3)
    out = pipe(image=image)
    holes = _holes_from(out["applied_transforms"])
    assert 2 <= len(holes) <= 4
    expected = np.zeros((H, W), bool)
    for x1, y1, x2, y2 in holes:
        assert 0 <= x1 < x2 <= W and 0 <= y1 < y2 <= H
        assert 0.2 * H - 1 <= y2 - y1 <= 0.4 * H + 1 and 0.1 * W - 1 <= x2 - x1 <= 0.2 * W + 1
        expected[y1:y2, x1:x2] = True
    painted = np.all(out["image"] == 0, axis=2)
    assert np.array_equal(painted, expected)
    assert np.array_equal(out["image"][~expected], image[~expected])  # nothing else changed
    assert image.min() >= 130  # the input array was not painted in place


def test_cutout_default_fill_is_zero_after_normalisation():
    image, _ = _scene()
    out = fill_holes(image, np.array([[10, 5, 30, 25]]), IMAGENET_MEAN_UINT8)
    norm = normalize_image(out)
    assert np.all(np.abs(norm[:, 5:25, 10:30]) < 0.01)
    assert np.all(norm[:, 30:, :] > 0.1)  # the textured rest is far from the mean


def test_lanes_unchanged_through_full_pipeline_with_cutout():
    image, lanes = _scene()
    big = dict(num_holes=(6, 6), hole_height=(0.3, 0.4), hole_width=(0.2, 0.3), p=1.0)
    ours = build_pipeline((H, W), augment=False, extra=[LaneCutout(fill=0, **big)])
    plain = build_pipeline((H, W), augment=False)
    _, reference = apply_pipeline(plain, image, lanes)
    for seed in range(5):
        ours.set_random_seed(seed)
        out, moved = apply_pipeline(ours, image, lanes)
        assert np.mean(np.all(out == 0, axis=2)) > 0.2  # large holes were cut...
        assert len(moved) == len(reference) == 3  # ...yet every lane keeps every point
        for got, want in zip(moved, reference):
            np.testing.assert_allclose(got, want)
    # the trap this transform exists for: CoarseDropout drops lane points under its holes
    coarse = A.CoarseDropout(num_holes_range=(6, 6), hole_height_range=(0.3, 0.4), hole_width_range=(0.2, 0.3), p=1.0)
    dropping = build_pipeline((H, W), augment=False, extra=[coarse])
    dropping.set_random_seed(0)
    _, cut = apply_pipeline(dropping, image, lanes)
    assert sum(len(lane) for lane in cut) < sum(len(lane) for lane in reference)


def test_cutout_with_augmentation_is_seeded_and_picklable():
    image, lanes = _scene()
    pipe = build_pipeline((H, W), augment=True, extra=[LaneCutout(p=1.0)])
    clone = pickle.loads(pickle.dumps(pipe))
    pipe.set_random_seed(7)
    clone.set_random_seed(7)
    a, la = apply_pipeline(pipe, image, lanes)
    b, lb = apply_pipeline(clone, image, lanes)
    assert np.array_equal(a, b) and len(la) == len(lb)


def test_cutout_rejects_bad_arguments():
    with pytest.raises(ValueError, match=r"LaneCutout.hole_height: expected a fraction of the image height in "
                                         r"\[0, 1\], or a \[min, max\] pair of them with min <= max, got \[0.5, 1.5\]"):
        LaneCutout(hole_height=[0.5, 1.5])
    with pytest.raises(ValueError, match="LaneCutout.num_holes: expected an integer >= 1, or a"):
        LaneCutout(num_holes=(3, 1))
    with pytest.raises(ValueError, match="LaneCutout.num_holes"):
        LaneCutout(num_holes=1.5)
    with pytest.raises(ValueError, match="LaneCutout.fill: expected one grey level or an RGB triple"):
        LaneCutout(fill=(1, 2))
    with pytest.raises(ValueError, match=r"LaneCutout.p: expected a probability in \[0, 1\], got 1.5"):
        LaneCutout(p=1.5)


def test_hsv_jitter_changes_colour_deterministically_and_keeps_lanes():
    image, lanes = _scene()
    pipe = build_pipeline((H, W), augment=False, extra=[hsv_jitter(p=1.0)])
    outs = []
    for seed in (5, 5, 6):
        pipe.set_random_seed(seed)
        out, moved = apply_pipeline(pipe, image, lanes)
        outs.append(out)
        assert len(moved) == 3
    assert np.array_equal(outs[0], outs[1])  # same seed, same jitter
    assert not np.array_equal(outs[0], outs[2])
    assert np.abs(outs[0].astype(int) - image.astype(int)).mean() > 3  # visibly changed
    t = hsv_jitter()
    assert t.hue_shift_limit == (-20, 20) and t.sat_shift_limit == (-40, 40) and t.p == 0.8
    with pytest.raises(ValueError, match=r"hsv_jitter.value: expected a shift limit in \[0, 255\], got -1"):
        hsv_jitter(value=-1)
    with pytest.raises(ValueError, match=r"hsv_jitter.hue: expected a shift limit in \[0, 180\], got 'a'"):
        hsv_jitter(hue="a")
