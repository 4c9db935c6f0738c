"""Input normalisation presets (data.normalize): each family's official input on a constructed pixel, the
defenses that work on pixels (cutout's fill, PGD's range) under each preset, and a checkpoint fed at evaluation
the normalisation it was trained with."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

import lanevil_train.conf
from lanevil_train.data.datasets import SyntheticLaneDataset
from lanevil_train.data.defenses import fill_holes
from lanevil_train.data.normalization import NORMALIZATIONS, normalization, normalize_image, unnormalize_image
from lanevil_train.data.transforms import LaneSampleProcessor
from lanevil_train.evaluation.streaming import stream_evaluate
from lanevil_train.tasks.builders import build_defense, build_model, checkpoint_model
from lanevil_train.tasks.detector.train import check_same_network

CONF = Path(lanevil_train.conf.__file__).parent

# The RGB pixel (10, 20, 30) under each preset, worked out by hand from the official formulas (data/normalization.py
# cites them): imagenet (p / 255 - mean) / std on RGB; laneatt and clrnet BGR / 255; ganet (BGR - mean) / std.
PIXEL = (10, 20, 30)
EXPECTED = {
    "imagenet": ((10 / 255 - 0.485) / 0.229, (20 / 255 - 0.456) / 0.224, (30 / 255 - 0.406) / 0.225),
    "laneatt": (30 / 255, 20 / 255, 10 / 255),
    "clrnet": (30 / 255, 20 / 255, 10 / 255),
    "ganet": ((30 - 75.3) / 50.5, (20 - 76.6) / 53.8, (10 - 77.6) / 54.3),
}


def test_every_preset_has_a_hand_worked_pixel():
    assert set(EXPECTED) == set(NORMALIZATIONS)


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_each_preset_on_a_constructed_pixel(name):
    image = np.zeros((2, 3, 3), np.uint8)  # one coloured pixel at row 1, column 2; black elsewhere
    image[1, 2] = PIXEL
    out = normalize_image(image, name)
    assert out.shape == (3, 2, 3) and out.dtype == np.float32 and out.flags["C_CONTIGUOUS"]
    np.testing.assert_allclose(out[:, 1, 2], EXPECTED[name], rtol=1e-6)
    np.testing.assert_allclose(out[:, 0, 0], normalize_image(np.zeros((1, 1, 3), np.uint8), name)[:, 0, 0])


def test_hand_values_spelled_out():
    """The same pixel with the numbers written out, so a wrong table entry cannot hide behind the formula."""
    rgb = np.array([[PIXEL]], np.uint8)
    np.testing.assert_allclose(normalize_image(rgb, "laneatt")[:, 0, 0], (0.117647, 0.078431, 0.039216), atol=1e-6)
    np.testing.assert_allclose(normalize_image(rgb, "ganet")[:, 0, 0], (-0.897030, -1.052045, -1.244936), atol=1e-6)
    np.testing.assert_allclose(normalize_image(rgb, "imagenet")[:, 0, 0], (-1.946656, -1.685574, -1.281569),
                               atol=1e-6)


def test_imagenet_is_bit_identical_to_the_former_normalisation():
    """Every existing checkpoint was trained on (x / 255 - mean) / std in float32: the default must not move a bit."""
    image = np.random.default_rng(0).integers(0, 256, (5, 7, 3), dtype=np.uint8)
    former = (image.astype(np.float32) / 255.0 - np.array([0.485, 0.456, 0.406], np.float32)) \
        / np.array([0.229, 0.224, 0.225], np.float32)
    assert np.array_equal(normalize_image(image), former.transpose(2, 0, 1))


@pytest.mark.parametrize("name", sorted(NORMALIZATIONS))
def test_unnormalize_gives_back_the_rgb_pixels(name):
    image = np.random.default_rng(1).integers(0, 256, (4, 6, 3), dtype=np.uint8)
    np.testing.assert_allclose(unnormalize_image(normalize_image(image, name), name) * 255, image, atol=1e-3)


def test_an_unknown_preset_is_an_error_naming_the_key():
    with pytest.raises(ValueError, match=r"^data\.normalize: expected one of imagenet, laneatt, clrnet, ganet, "
                                         r"got 'caffe'$"):
        normalize_image(np.zeros((1, 1, 3), np.uint8), "caffe")


# ----------------------------------------------------------------------------------- defenses working on pixels

def _defense_cfg(defense: str, normalize: str):
    return OmegaConf.create({"seed": 0, "data": {"normalize": normalize},
                             "defense": OmegaConf.load(CONF / "defense" / f"{defense}.yaml")})


@pytest.mark.parametrize("name", sorted(NORMALIZATIONS))
def test_the_cutout_fill_is_zero_after_each_preset(name):
    (cutout,) = build_defense(_defense_cfg("cutout", name))["transforms"]
    image = np.full((8, 10, 3), 200, np.uint8)
    out = normalize_image(fill_holes(image, np.array([[2, 1, 7, 6]]), cutout.cutout_fill), name)
    preset = normalization(name)
    half_grey = 0.5 / preset.divisor / np.asarray(preset.std)  # the uint8 fill is the mean rounded
    assert np.all(np.abs(out[:, 1:6, 2:7]) <= half_grey[:, None, None] + 1e-6)
    assert np.all(np.abs(out[:, 0, :]) > 10 * half_grey[:, None])  # outside the hole: far from 0


def test_a_cutout_fill_set_in_the_config_is_kept():
    cfg = _defense_cfg("cutout", "ganet")
    cfg.defense.transforms[0].fill = 7
    assert build_defense(cfg)["transforms"][0].cutout_fill == (7.0,)


@pytest.mark.parametrize("name", sorted(NORMALIZATIONS))
def test_pgd_clamps_to_the_normalised_black_and_white_of_each_preset(name):
    # the preset is the trained model's (its build config's), whatever data.normalize says
    pgd = build_defense(_defense_cfg("pgd", "imagenet"))["callback"]
    images = torch.zeros(1, 3, 2, 2)
    eps, _, low, high = pgd.bounds(images, build_model({**SPEC, "normalize": name}))
    black, white = (normalize_image(np.full((1, 1, 3), v, np.uint8), name)[:, 0, 0] for v in (0, 255))
    np.testing.assert_allclose(low.flatten().numpy(), black, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(high.flatten().numpy(), white, rtol=1e-5, atol=1e-6)
    # eps = 4/255 of a pixel: the gap between the grey levels 0 and 4 in the tensor's units
    four = normalize_image(np.full((1, 1, 3), 4, np.uint8), name)[:, 0, 0]
    np.testing.assert_allclose(eps.flatten().numpy(), four - black, rtol=1e-4)


# --------------------------------------------------------------------------------- checkpoints remember theirs

SPEC = {
    "model": {"name": "laneatt", "head": {"_target_": "lanevil_train.models.laneatt.LaneATTHead", "max_lanes": 6}},
    "backbone": {"_target_": "lanevil_train.models.backbones.build_backbone", "name": "resnet18", "out_indices": [3]},
    "input_size": [64, 160],
    "crop_top": 0.0,
}


def test_a_checkpoint_evaluates_with_the_normalisation_it_was_trained_with(tmp_path, monkeypatch):
    torch.manual_seed(0)
    trained = build_model({**SPEC, "normalize": "laneatt"})
    path = tmp_path / "last.ckpt"
    torch.save({"state_dict": trained.state_dict(), "lanevil_model": trained.build_config}, path)
    # the evaluation's own data.normalize (the default imagenet) does not apply: the checkpoint's build config does
    cfg = OmegaConf.create({"ckpt_path": str(path), "data": {"normalize": "imagenet", "input_size": [64, 160]}})
    model = checkpoint_model(cfg)
    assert model.build_config["normalize"] == "laneatt"

    seen = []
    forward = model.forward

    def spy(images):
        seen.append(images.clone())
        return forward(images)

    monkeypatch.setattr(model, "forward", spy)
    dataset = SyntheticLaneDataset(num_scenes=1, first_seed=0, size=(90, 160), cache=False)
    stream_evaluate(model, dataset, tmp_path / "per_image.jsonl", {"model": "m", "dataset": "d"}, progress="none")
    fed = seen[0][0].numpy()
    expected = LaneSampleProcessor((64, 160), augment=False, normalize="laneatt")(dataset[0])["image"]
    np.testing.assert_array_equal(fed, expected)
    assert 0.0 <= fed.min() and fed.max() <= 1.0  # BGR / 255, not ImageNet-normalised
    imagenet = LaneSampleProcessor((64, 160), augment=False)(dataset[0])["image"]
    np.testing.assert_allclose(fed, imagenet[::-1] * np.array([0.225, 0.224, 0.229])[:, None, None]
                               + np.array([0.406, 0.456, 0.485])[:, None, None], atol=1e-5)


def test_resuming_with_another_normalisation_is_refused(tmp_path):
    saved = {**SPEC, "normalize": "ganet"}
    with pytest.raises(ValueError, match=r"data\.normalize was 'ganet', now 'imagenet'"):
        check_same_network({"lanevil_model": saved}, {**SPEC, "normalize": "imagenet"}, tmp_path / "last.ckpt")
    # a build config older than the key was trained on imagenet: resuming it with imagenet is the same network
    check_same_network({"lanevil_model": SPEC}, {**SPEC, "normalize": "imagenet"}, tmp_path / "last.ckpt")


def test_training_records_data_normalize_and_feeds_it_to_both_splits(hydra_conf):
    from hydra import compose

    from lanevil_train.tasks.builders import build_datamodule, model_config
    from tests.tasks.cli_helpers import TINY

    cfg = compose(config_name="config", overrides=[*TINY, "data.normalize=ganet"])
    model = build_model(model_config(cfg))
    assert model.build_config["normalize"] == "ganet"  # saved in every checkpoint (LaneDetector.on_save_checkpoint)
    datamodule = build_datamodule(cfg, ("train", "val"), model)
    assert datamodule.train_processor.normalize == datamodule.eval_processor.normalize == "ganet"


def test_the_closed_loop_feeds_a_detector_its_own_normalisation(monkeypatch):
    from lanevil_train.closed_loop.policies import DetectorPolicy

    torch.manual_seed(0)
    model = build_model({**SPEC, "normalize": "ganet"})
    seen = []
    monkeypatch.setattr(model, "forward", lambda images: seen.append(images.clone()) or {})  # what it is fed
    monkeypatch.setattr(model, "decode_lanes", lambda raw, input_size, sizes, with_scores=False: [[]])
    image = np.random.default_rng(2).integers(0, 256, (64, 160, 3), dtype=np.uint8)
    DetectorPolicy(model).lanes(image)
    np.testing.assert_array_equal(seen[0][0].numpy(), normalize_image(image, "ganet"))


def test_a_cutout_among_data_train_transforms_fills_with_the_models_mean_colour(hydra_conf):
    from hydra import compose

    from lanevil_train.tasks.builders import build_datamodule, model_config
    from tests.tasks.cli_helpers import TINY

    cfg = compose(config_name="config", overrides=[*TINY, "data.normalize=laneatt",
                                                   "data.train_transforms=[{_target_: lanevil_train.data.defenses"
                                                   ".LaneCutout}]"])
    datamodule = build_datamodule(cfg, ("train",), build_model(model_config(cfg)))
    (cutout,) = [t for t in datamodule.train_processor.pipeline.transforms if type(t).__name__ == "LaneCutout"]
    assert cutout.cutout_fill == (0.0, 0.0, 0.0)  # BGR / 255: black is 0
