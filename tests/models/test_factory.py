"""The Hydra-free factory (models/factory.py) and the Python API: a spec builds the network, a checkpoint of every
family loads back with the same weights and the same lanes, det.predict maps lanes to each image's own pixels,
the preprocessor is the evaluation's, and bad specs are refused by name."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import lanevil_train
from lanevil_train.data.preprocessor import Preprocessor, lanes_to_original
from lanevil_train.models.factory import DetectorSpec, create_detector, load_detector
from lanevil_train.tasks.builders import model_config
from tests.models.test_families import BACKBONE, FAMILIES, NARROW
from tests.tasks.cli_helpers import composed

SIZE = (96, 256)


def _spec(family: str, *overrides: str) -> DetectorSpec:
    cfg = composed([f"model={family}", f"backbone={BACKBONE.get(family, 'resnet18')}",
                    f"data.input_size=[{SIZE[0]},{SIZE[1]}]", "data.max_lanes=4", *NARROW.get(family, []),
                    *overrides])
    return DetectorSpec.from_build_config(model_config(cfg))


def _road(height: int, width: int, seed: int = 0) -> np.ndarray:
    """A BGR road-like image: grey asphalt, two bright lines."""
    import cv2

    rng = np.random.default_rng(seed)
    image = np.full((height, width, 3), 90, np.uint8)
    image[: height // 3] = (200, 170, 140)
    image = np.clip(image + rng.normal(0, 6, image.shape), 0, 255).astype(np.uint8)
    for x0, x1 in ((0.25, 0.45), (0.8, 0.55)):
        cv2.line(image, (int(x0 * width), height - 1), (int(x1 * width), height // 3), (240, 240, 240),
                 max(2, width // 100))
    return image


def test_the_api_is_at_the_top():
    assert lanevil_train.load_detector is load_detector
    from lanevil_train.illusions.api import apply_illusion

    assert lanevil_train.apply_illusion is apply_illusion
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        lanevil_train.nothing  # noqa: B018


@pytest.mark.parametrize("family", FAMILIES)
def test_a_checkpoint_of_every_family_loads_back_with_its_weights_and_lanes(family, tmp_path):
    """create_detector(spec) -> a Lightning-style checkpoint (state_dict + lanevil_model, as task=train writes) ->
    load_detector: the same spec, the same weights, the same predicted lanes and scores on a 1280x720 image."""
    torch.manual_seed(0)
    model = create_detector(_spec(family)).eval()
    path = tmp_path / "last.ckpt"
    torch.save({"state_dict": model.state_dict(), "lanevil_model": model.build_config}, path)
    loaded = load_detector(path)
    assert not loaded.training and loaded.build_config == model.build_config
    for (name, a), (_, b) in zip(sorted(model.state_dict().items()), sorted(loaded.state_dict().items())):
        assert torch.equal(a, b), name
    image = _road(720, 1280)
    inputs = model.preprocessor.batch([image])
    with torch.no_grad():
        for key, value in model(inputs).items():
            assert torch.equal(value, loaded(inputs)[key]), key
    mine, theirs = model.predict(image), loaded.predict(image)
    assert len(mine) == len(theirs)
    for a, b in zip(mine, theirs):
        np.testing.assert_array_equal(a.points, b.points)
        assert a.score == b.score and 0.0 <= a.score <= 1.0


def test_predict_maps_lanes_to_each_images_own_size():
    """The same road at 1920x1080 and at 640x360: det.predict's points are the decoded input-pixel lanes mapped
    through the crop and resize to that image (x * W / w, y * (H - cut) / h + cut), batched as one call."""
    torch.manual_seed(0)
    det = create_detector(_spec("scnn", "data.crop_top=0.25", "model.decode.exist_threshold=0.0",
                                "model.decode.prob_threshold=0.0")).eval()  # random weights that give lanes
    big, small = _road(1080, 1920), _road(360, 640)
    both = det.predict([big, small])
    preprocessor = det.preprocessor
    assert preprocessor.crop_top == 0.25 and preprocessor.input_size == SIZE
    for image, lanes in zip((big, small), both):
        inputs = preprocessor.batch([image])
        with torch.no_grad():
            decoded = det.head.decode(det(inputs), **det.decode_kwargs)[0]
        expected = lanes_to_original(decoded, SIZE, image.shape[:2], 0.25)
        assert len(lanes) == len(expected) > 0
        for lane, points in zip(lanes, expected):
            np.testing.assert_allclose(lane.points, points, atol=1e-3)  # a batch of 2 vs 1: float32 sums
            cut = round(0.25 * image.shape[0])
            assert lane.points[:, 1].min() >= cut - 1e-6 and lane.points[:, 1].max() <= image.shape[0]
    # the same lanes whichever size: 1920x1080 is 3x 640x360 (the inputs differ only by the resize's rounding)
    single = det.predict(small)
    assert [lane.score for lane in single] == [lane.score for lane in both[1]]


@pytest.mark.parametrize("resize", ["area", "pil_bilinear", "cubic"])
def test_the_preprocessor_is_the_evaluations(resize):
    """Preprocessor.image (BGR in) equals what the evaluation's sample processor feeds the network (RGB in)."""
    preprocessor = Preprocessor((96, 256), crop_top=0.22, normalize="imagenet", resize=resize)
    bgr = _road(720, 1280, seed=3)
    sample = {"image": bgr[:, :, ::-1].copy(), "lanes": [], "meta": {}}
    np.testing.assert_array_equal(preprocessor.image(bgr), preprocessor.sample_processor()(sample)["image"])
    np.testing.assert_array_equal(preprocessor.image(bgr[:, :, ::-1].copy(), color="rgb"), preprocessor.image(bgr))


def test_bad_specs_and_images_are_refused_by_name(tmp_path):
    spec = _spec("laneatt")
    config = spec.build_config()
    with pytest.raises(ValueError, match="normalize='imagenette': expected one of"):
        DetectorSpec.from_build_config({**config, "normalize": "imagenette"})
    with pytest.raises(ValueError, match=r"input_size: expected \[height, width\], two integers >= 8"):
        DetectorSpec.from_build_config({**config, "input_size": [96]})
    with pytest.raises(ValueError, match="needs model, backbone, input_size"):
        DetectorSpec.from_build_config({"crop_top": 0.1})
    bad_head = {**config, "model": {**config["model"], "head": {**config["model"]["head"], "n_offsets": -3}}}
    with pytest.raises(ValueError, match=r"^model\.head"):
        create_detector(DetectorSpec.from_build_config(bad_head))
    with pytest.raises(ValueError, match="color='bgra'"):
        Preprocessor(SIZE).image(_road(64, 64), color="bgra")
    with pytest.raises(ValueError, match="uint8 HxWx3"):
        Preprocessor(SIZE).image(np.zeros((64, 64), np.uint8))
    path = tmp_path / "weights.pt"
    torch.save({"state_dict": create_detector(spec).state_dict()}, path)  # no build config
    with pytest.raises(ValueError, match="without its build config"):
        load_detector(path)
    assert load_detector(path, spec=spec).build_config == spec.build_config()
