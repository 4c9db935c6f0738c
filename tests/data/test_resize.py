"""Image resize filters (data.resize): each filter gives what its library gives, lanes are scaled the same
whatever the filter, a checkpoint remembers its filter and is evaluated with it, and the default (area) leaves
the former behaviour and run identities as they were."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from PIL import Image

import lanevil_train.conf
from lanevil_train.data.datasets import SyntheticLaneDataset
from lanevil_train.data.normalization import normalize_image
from lanevil_train.data.resize import RESIZE_FILTERS, resize_image
from lanevil_train.data.transforms import LaneSampleProcessor, apply_pipeline, build_pipeline
from lanevil_train.evaluation.streaming import run_identity, stream_evaluate
from lanevil_train.tasks.builders import build_model, checkpoint_model, model_config
from lanevil_train.tasks.detector.train import check_same_network

CONF = Path(lanevil_train.conf.__file__).parent
IMAGE = np.random.default_rng(0).integers(0, 256, (37, 61, 3), dtype=np.uint8)  # odd sizes: no exact ratio
SIZE = (16, 24)  # (H, W)


def _library(name: str, image: np.ndarray, height: int, width: int) -> np.ndarray:
    """What each library gives, called directly."""
    if name == "pil_bilinear":
        return np.asarray(Image.fromarray(image).resize((width, height), Image.BILINEAR))
    flag = {"area": cv2.INTER_AREA, "linear": cv2.INTER_LINEAR, "cubic": cv2.INTER_CUBIC}[name]
    return cv2.resize(image, (width, height), interpolation=flag)


def test_the_filters():
    assert list(RESIZE_FILTERS) == ["area", "linear", "cubic", "pil_bilinear"]


@pytest.mark.parametrize("name", list(RESIZE_FILTERS))
def test_each_filter_gives_what_its_library_gives(name):
    expected = _library(name, IMAGE, *SIZE)
    np.testing.assert_array_equal(resize_image(IMAGE, *SIZE, name), expected)
    out, _ = apply_pipeline(build_pipeline(SIZE, augment=False, resize=name), IMAGE, [])
    assert out.dtype == np.uint8
    np.testing.assert_array_equal(out, expected)
    item = LaneSampleProcessor(SIZE, augment=False, resize=name)({"image": IMAGE, "lanes": [], "meta": {}})
    np.testing.assert_array_equal(item["image"], normalize_image(expected))


def test_the_filters_differ():
    """Otherwise the tests above could not tell them apart."""
    outs = [_library(name, IMAGE, *SIZE) for name in RESIZE_FILTERS]
    assert all(not np.array_equal(a, b) for i, a in enumerate(outs) for b in outs[i + 1:])


def test_lanes_are_scaled_the_same_whatever_the_filter():
    lane = np.array([[5.0, 36.0], [20.0, 20.0], [40.0, 3.0]])
    moved = [apply_pipeline(build_pipeline(SIZE, augment=False, resize=name), IMAGE, [lane])[1]
             for name in RESIZE_FILTERS]
    for lanes in moved:
        np.testing.assert_allclose(lanes[0], lane * [24 / 61, 16 / 37], atol=1e-6)


def test_the_default_is_area_as_before():
    default = LaneSampleProcessor(SIZE, augment=False)({"image": IMAGE, "lanes": [], "meta": {}})["image"]
    np.testing.assert_array_equal(default, normalize_image(cv2.resize(IMAGE, SIZE[::-1], interpolation=cv2.INTER_AREA)))


def test_an_unknown_filter_is_an_error_naming_the_key():
    message = r"^data\.resize: expected one of area, linear, cubic, pil_bilinear, got 'bicubic'$"
    with pytest.raises(ValueError, match=message):
        LaneSampleProcessor(SIZE, augment=False, resize="bicubic")
    with pytest.raises(ValueError, match=message):
        resize_image(IMAGE, *SIZE, "bicubic")
    cfg = OmegaConf.create({"model": {}, "backbone": {}, "data": {"input_size": [64, 160], "resize": "bicubic"}})
    with pytest.raises(ValueError, match=message):
        model_config(cfg)


# --------------------------------------------------------------------------------- checkpoints remember theirs

SPEC = {
    "model": {"name": "laneatt", "head": {"_target_": "lanevil_train.models.laneatt.LaneATTHead", "max_lanes": 6}},
    "backbone": {"_target_": "lanevil_train.models.backbones.build_backbone", "name": "resnet18", "out_indices": [3]},
    "input_size": [64, 160],
    "crop_top": 0.0,
}


def test_a_checkpoint_evaluates_with_the_filter_it_was_trained_with(tmp_path, monkeypatch):
    torch.manual_seed(0)
    trained = build_model({**SPEC, "resize": "pil_bilinear"})
    path = tmp_path / "last.ckpt"
    torch.save({"state_dict": trained.state_dict(), "lanevil_model": trained.build_config}, path)
    # the evaluation's own data.resize (area) does not apply: the checkpoint's build config does
    cfg = OmegaConf.create({"ckpt_path": str(path), "data": {"resize": "area", "input_size": [64, 160]}})
    model = checkpoint_model(cfg)
    assert model.build_config["resize"] == "pil_bilinear"

    seen = []
    forward = model.forward
    monkeypatch.setattr(model, "forward", lambda images: seen.append(images.clone()) or forward(images))
    dataset = SyntheticLaneDataset(num_scenes=1, first_seed=0, size=(90, 160), cache=False)
    stream_evaluate(model, dataset, tmp_path / "per_image.jsonl", {"model": "m", "dataset": "d"}, progress="none")
    fed = seen[0][0].numpy()
    np.testing.assert_array_equal(fed, normalize_image(_library("pil_bilinear", dataset[0]["image"], 64, 160)))
    assert not np.array_equal(fed, normalize_image(_library("area", dataset[0]["image"], 64, 160)))


def test_run_identities_name_the_filter_only_when_not_the_default():
    torch.manual_seed(0)
    label = {"model": "m", "dataset": "d"}
    before = run_identity(build_model(SPEC), label)  # a build config older than the key
    torch.manual_seed(0)
    area = run_identity(build_model({**SPEC, "resize": "area"}), label)
    assert "resize" not in before and area == before  # results files written before the key still match
    torch.manual_seed(0)
    cubic = run_identity(build_model({**SPEC, "resize": "cubic"}), label)
    assert cubic == {**before, "resize": "cubic"}


def test_resuming_with_another_filter_is_refused(tmp_path):
    with pytest.raises(ValueError, match=r"data\.resize was 'cubic', now 'area'"):
        check_same_network({"lanevil_model": {**SPEC, "resize": "cubic"}}, {**SPEC, "resize": "area"},
                           tmp_path / "last.ckpt")
    # a build config older than the key was trained on area: resuming it with area is the same network
    check_same_network({"lanevil_model": SPEC}, {**SPEC, "resize": "area"}, tmp_path / "last.ckpt")


def test_training_records_data_resize_and_feeds_it_to_both_splits(hydra_conf):
    from hydra import compose

    from lanevil_train.tasks.builders import build_datamodule
    from tests.tasks.cli_helpers import TINY

    default = compose(config_name="config", overrides=TINY)
    assert model_config(default)["resize"] == "area"
    cfg = compose(config_name="config", overrides=[*TINY, "data.resize=linear"])
    model = build_model(model_config(cfg))
    assert model.build_config["resize"] == "linear"  # saved in every checkpoint (LaneDetector.on_save_checkpoint)
    datamodule = build_datamodule(cfg, ("train", "val"), model)
    assert datamodule.train_processor.resize == datamodule.eval_processor.resize == "linear"


def test_the_closed_loop_feeds_a_detector_its_own_filter(monkeypatch):
    from lanevil_train.closed_loop.policies import DetectorPolicy

    torch.manual_seed(0)
    model = build_model({**SPEC, "resize": "cubic"})
    seen = []
    monkeypatch.setattr(model, "forward", lambda images: seen.append(images.clone()) or {})  # what it is fed
    monkeypatch.setattr(model, "decode_lanes", lambda raw, input_size, sizes, with_scores=False: [[]])
    image = np.random.default_rng(2).integers(0, 256, (90, 200, 3), dtype=np.uint8)
    DetectorPolicy(model).lanes(image)
    np.testing.assert_array_equal(seen[0][0].numpy(), normalize_image(_library("cubic", image, 64, 160)))


# Each official release's test-time filter (the sources are cited in the experiment configs).
OFFICIAL = {"ufld": "pil_bilinear", "scnn": "pil_bilinear", "bezierlanenet": "pil_bilinear", "laneatt": "cubic",
            "clrnet": "cubic", "ganet": "linear", "ganet_large": "linear", "clrernet": "linear"}


@pytest.mark.parametrize("path", sorted((CONF / "experiment").glob("official_*.yaml")), ids=lambda p: p.stem)
def test_each_official_config_sets_its_releases_filter(path):
    family = path.stem.removeprefix("official_").rsplit("_", 1)[0]
    assert OmegaConf.load(path).data.resize == OFFICIAL[family]
