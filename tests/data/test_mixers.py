"""Batch mixers: MixUp's exact blend and folded lambda, lane-aware copy-paste, and the mixing collate."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch

from lanevil_train.data.datamodule import LaneDataModule, MixingCollate, collate_lanes
from lanevil_train.data.mixers import LaneCopyPaste, MixUp, lane_band_mask, lanes_apart

H, W = 64, 160


def _vertical(x: float, y_top: float = 0.0, y_bottom: float = H - 1) -> np.ndarray:
    return np.array([[x, y_bottom], [x, y_top]], dtype=np.float64)


def _item(value: float, lanes: list[np.ndarray], seed: int = 0) -> dict:
    """A processed item: a textured float image around `value` (so images differ everywhere)."""
    rng = np.random.default_rng(seed)
    image = (value + 0.1 * rng.standard_normal((3, H, W))).astype(np.float32)
    return {"image": image, "lanes": [lane * 2 for lane in lanes], "input_lanes": list(lanes),
            "meta": {"case_id": f"c{seed}"}}


def _batch(n: int = 6) -> list[dict]:
    return [_item(float(i), [_vertical(30.0 + 10 * i)], seed=i) for i in range(n)]


# ---------------------------------------------------------------- MixUp

def test_mixup_blends_with_folded_lambda_and_keeps_labels():
    items = _batch()
    originals = [it["image"].copy() for it in items]
    mixer = MixUp(alpha=0.4, p=0.8, seed=11)
    out = mixer(items)
    partners, lams = MixUp(alpha=0.4, p=0.8, seed=11).plan(len(items), np.random.default_rng([11, 0]))
    assert (partners >= 0).sum() >= 3  # the seed mixes most of the batch
    for i, (got, j, lam) in enumerate(zip(out, partners, lams)):
        assert got["input_lanes"] is items[i]["input_lanes"] and got["lanes"] is items[i]["lanes"]
        if j < 0:
            assert lam == 1.0 and np.array_equal(got["image"], originals[i])
            continue
        assert j != i and 0.5 <= lam < 1.0
        expected = (lam * originals[i].astype(np.float64) + (1 - lam) * originals[j]).astype(np.float32)
        np.testing.assert_array_equal(got["image"], expected)
        # the image is dominated by itself: its level is nearer its own than the partner's
        assert abs(got["image"].mean() - i) <= abs(got["image"].mean() - j)
    for it, orig in zip(items, originals):
        assert np.array_equal(it["image"], orig)  # inputs not modified in place


def test_mixup_lambda_is_folded_beta():
    lams = MixUp(alpha=1.0, p=1.0).plan(20000, np.random.default_rng(0))[1]
    assert lams.min() >= 0.5 and lams.max() <= 1.0
    assert abs(lams.mean() - 0.75) < 0.01  # max(U, 1 - U) for Beta(1, 1) = U(0, 1)
    small = MixUp(alpha=0.2, p=1.0).plan(20000, np.random.default_rng(0))[1]
    assert abs(small.mean() - 0.90) < 0.01


def test_mixup_p0_and_single_image_leave_images_untouched():
    items = _batch(4)
    out = MixUp(p=0.0, seed=1)(items)
    assert all(a is b for a, b in zip(out, items))
    one = _batch(1)
    assert MixUp(p=1.0, seed=1)(one)[0] is one[0]
    with pytest.raises(ValueError, match=r"MixUp.alpha: expected a number > 0 \(lambda ~ Beta\(alpha, alpha\)\), "
                                         r"got 0.0"):
        MixUp(alpha=0.0)


def test_mixer_generator_seeded_per_process_and_reset_on_pickle():
    a, b = MixUp(p=1.0, seed=4), MixUp(p=1.0, seed=4)
    assert np.array_equal(a(_batch())[0]["image"], b(_batch())[0]["image"])
    torch.manual_seed(123)
    unseeded = MixUp(p=1.0)
    first = unseeded.generator().random()
    assert first == np.random.default_rng(123).random()
    clone = pickle.loads(pickle.dumps(unseeded))
    assert clone._rng is None  # a worker builds its own generator instead of replaying the parent's


# ---------------------------------------------------------------- copy-paste

def test_copypaste_pastes_band_and_label_of_a_far_donor_lane():
    target = _item(0.0, [_vertical(40.0)], seed=1)
    donor = _item(5.0, [_vertical(120.0)], seed=2)
    mixer = LaneCopyPaste(p=1.0, band=4.0, min_gap=20.0, max_lanes=4)
    out = mixer.paste(target, donor)
    band = np.zeros((H, W), bool)
    band[:, 116:125] = True  # within 4 px of x=120
    np.testing.assert_array_equal(out["image"][:, band], donor["image"][:, band])
    np.testing.assert_array_equal(out["image"][:, ~band], target["image"][:, ~band])
    assert [lane[0, 0] for lane in out["input_lanes"]] == [40.0, 120.0]
    np.testing.assert_array_equal(out["input_lanes"][1], donor["input_lanes"][0])
    assert len(out["lanes"]) == 1 and out["lanes"] is target["lanes"]  # scoring GT stays
    assert len(target["input_lanes"]) == 1 and target["image"].mean() < 1  # inputs untouched


def test_copypaste_skips_a_donor_lane_too_close_to_a_target_lane():
    target = _item(0.0, [_vertical(40.0)], seed=1)
    # slanted donor lane: 60 px from the target at the bottom but only 10 px at the top
    slanted = np.array([[100.0, H - 1], [50.0, 0.0]])
    donor = _item(5.0, [slanted], seed=2)
    mixer = LaneCopyPaste(p=1.0, band=4.0, min_gap=20.0)
    assert mixer.paste(target, donor) is target
    # a lane that only shares no row with the target lane can be pasted even if close in x
    short_target = _item(0.0, [_vertical(40.0, y_top=40.0)], seed=1)
    short_donor = _item(5.0, [_vertical(45.0, y_top=0.0, y_bottom=30.0)], seed=2)
    assert len(mixer.paste(short_target, short_donor)["input_lanes"]) == 2
    assert not lanes_apart(slanted, [_vertical(40.0)], 20.0, H)
    assert lanes_apart(slanted, [_vertical(40.0)], 10.0, H)


def test_copypaste_respects_max_lanes_and_max_paste():
    target = _item(0.0, [_vertical(20.0), _vertical(60.0)], seed=1)
    donor = _item(5.0, [_vertical(100.0), _vertical(130.0), _vertical(155.0)], seed=2)
    three = LaneCopyPaste(p=1.0, band=3.0, min_gap=20.0, max_lanes=3, max_paste=3).paste(target, donor)
    assert [lane[0, 0] for lane in three["input_lanes"]] == [20.0, 60.0, 100.0]
    four = LaneCopyPaste(p=1.0, band=3.0, min_gap=20.0, max_lanes=8, max_paste=3).paste(target, donor)
    # 155 is only 25 px from 130 -> pasted; all three fit
    assert [lane[0, 0] for lane in four["input_lanes"]] == [20.0, 60.0, 100.0, 130.0, 155.0]
    one = LaneCopyPaste(p=1.0, band=3.0, min_gap=20.0, max_lanes=8, max_paste=1).paste(target, donor, order=[1, 0, 2])
    assert [lane[0, 0] for lane in one["input_lanes"]] == [20.0, 60.0, 130.0]
    full = LaneCopyPaste(p=1.0, band=3.0, min_gap=20.0, max_lanes=2).paste(target, donor)
    assert full is target
    with pytest.raises(ValueError, match="band"):
        LaneCopyPaste(band=10.0, min_gap=5.0)
    with pytest.raises(ValueError, match="LaneCopyPaste.band: expected a number of input pixels >= 0, got -1"):
        LaneCopyPaste(band=-1)
    with pytest.raises(ValueError, match="LaneCopyPaste.max_paste: expected an integer >= 1, got 0"):
        LaneCopyPaste(max_paste=0)
    with pytest.raises(ValueError, match=r"LaneCopyPaste.p: expected a probability in \[0, 1\], got 2"):
        LaneCopyPaste(p=2)


def test_copypaste_batch_call_never_exceeds_max_lanes_and_keeps_gaps():
    items = [_item(float(i), [_vertical(20.0 + 25 * (i % 3) + 40 * k) for k in range(1 + i % 3)], seed=i)
             for i in range(8)]
    mixer = LaneCopyPaste(p=1.0, band=4.0, min_gap=12.0, max_lanes=3, max_paste=2, seed=0)
    out = mixer(items)
    grew = 0
    for before, after in zip(items, out):
        assert len(after["input_lanes"]) <= max(3, len(before["input_lanes"]))
        grew += len(after["input_lanes"]) > len(before["input_lanes"])
        xs = [lane[0, 0] for lane in after["input_lanes"]]
        assert xs == sorted(xs) and np.all(np.diff(xs) >= 12.0)
    assert grew >= 3


def test_band_mask_is_the_euclidean_band():
    mask = lane_band_mask(np.array([[80.0, 50.0], [80.0, 10.0]]), H, W, 5.0)
    assert mask[30, 75:86].all() and not mask[30, 74] and not mask[30, 86]
    assert mask[5, 80] and not mask[4, 80] and mask[55, 80] and not mask[56, 80]  # round caps
    assert not lane_band_mask(np.array([[500.0, 50.0], [500.0, 10.0]]), H, W, 5.0).any()


# ---------------------------------------------------------------- datamodule wiring

def _samples(n: int) -> list[dict]:
    out = []
    for i in range(n):
        image = np.random.default_rng(i).integers(0, 256, size=(H, W, 3), dtype=np.uint8)  # independent textures
        out.append({"image": image, "lanes": [_vertical(30.0 + 5 * i)], "meta": {"case_id": f"s{i}"}})
    return out


def _count(lanes: list[np.ndarray], meta: dict | None = None) -> dict[str, np.ndarray]:
    return {"count": np.array([len(lanes), sum(lane[0, 0] for lane in lanes)], np.float32)}


def test_datamodule_mixer_encodes_mixed_lanes_and_leaves_eval_alone():
    data = _samples(4)
    mixer = LaneCopyPaste(p=1.0, band=3.0, min_gap=4.0, max_lanes=4, seed=0)
    # donor lanes at x=30..45 are >= 5 px apart, so every image gains one pasted lane
    dm = LaneDataModule(data, data, data, input_size=(H, W), batch_size=4, augment=False, encode=_count,
                        train_mixer=mixer)
    batch = next(iter(dm.train_dataloader()))
    counts = [len(lanes) for lanes in batch["input_lanes"]]
    assert counts == [2, 2, 2, 2]
    for target, lanes in zip(batch["targets"]["count"], batch["input_lanes"]):
        np.testing.assert_allclose(target.numpy(), _count(lanes)["count"])
    assert [len(lanes) for lanes in batch["lanes"]] == [1, 1, 1, 1]  # scoring GT untouched
    for split in ("val", "test"):
        loader = dm.val_dataloader() if split == "val" else dm.test_dataloader()
        plain = next(iter(loader))
        assert [len(lanes) for lanes in plain["input_lanes"]] == [1, 1, 1, 1]
        np.testing.assert_allclose(plain["targets"]["count"][:, 0].numpy(), 1.0)
        expected = collate_lanes([dm.eval_processor(s) for s in data])
        assert torch.equal(plain["images"], expected["images"])
    no_mix = LaneDataModule(data, None, None, input_size=(H, W), batch_size=4, augment=False, encode=_count)
    assert no_mix.train_dataloader().collate_fn is collate_lanes
    assert isinstance(dm.train_dataloader().collate_fn, MixingCollate)


def test_datamodule_mixer_runs_in_a_worker():
    data = _samples(4)
    dm = LaneDataModule(data, None, None, input_size=(H, W), batch_size=4, augment=False, encode=_count,
                        num_workers=1, train_mixer=MixUp(alpha=1.0, p=1.0, seed=3))
    batch = next(iter(dm.train_dataloader()))
    assert tuple(batch["images"].shape) == (4, 3, H, W)
    plain = {s["meta"]["case_id"]: dm.train_processor(s)["image"] for s in data}
    for image, meta in zip(batch["images"].numpy(), batch["meta"]):
        own = plain[meta["case_id"]]
        assert np.abs(image - own).mean() > 0.01  # p=1: every image was blended with another one
        explained = []
        for case, other in plain.items():  # find lam with image == lam * own + (1 - lam) * other
            if case == meta["case_id"]:
                continue
            diff = (own - other).astype(np.float64)
            lam = float(np.sum((image - other) * diff) / np.sum(diff * diff))  # least squares
            if np.allclose(image, lam * own + (1 - lam) * other, atol=1e-5):
                explained.append(lam)
        assert len(explained) == 1 and 0.5 <= explained[0] < 1.0  # one partner, folded lambda
    np.testing.assert_allclose(batch["targets"]["count"][:, 0].numpy(), 1.0)
