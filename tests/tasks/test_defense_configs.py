"""Every defense= config instantiates its parts and trains a LaneATT step through task=train."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_module

from lanevil_train.callbacks import AttentionAreaMixing, PGDAdversarialTraining
from lanevil_train.data.defenses import LaneCutout
from lanevil_train.data.mixers import LaneCopyPaste, MixUp
from lanevil_train.tasks.builders import build_defense
from lanevil_train.tasks.detector.train import train
from tests.tasks.cli_helpers import TINY

DEFENSE_DIR = Path(__file__).resolve().parents[2] / "lanevil_train" / "conf" / "defense"
EXPECTED = {"none": (0, None, None), "cutout": (1, None, None), "hsv": (1, None, None), "mixup": (0, MixUp, None),
            "copypaste": (0, LaneCopyPaste, None), "pgd": (0, None, PGDAdversarialTraining),
            "aam": (0, None, AttentionAreaMixing), "aam++": (0, None, AttentionAreaMixing)}


def compose_defense(name: str, tmp_path: Path, extra: list[str] = ()):
    overrides = [*TINY, f"defense={name}", "trainer.max_steps=2", "task.test_after_fit=false", "logger=none",
                 f"output_dir={tmp_path}", "data.train.num_scenes=4", *extra]
    with initialize_config_module(config_module="lanevil_train.conf", version_base="1.3"):
        return compose(config_name="config", overrides=overrides)


VLM_DEFENSES = {"pat++", "pat", "self_reminder", "mida"}  # textual (and cross-modal) defenses of VLMs


def test_the_defense_configs_are_the_papers_baselines():
    assert {p.stem for p in DEFENSE_DIR.glob("*.yaml")} == set(EXPECTED) | VLM_DEFENSES


def test_a_textual_defense_is_refused_for_a_lane_detector(tmp_path):
    with pytest.raises(ValueError, match=r"defense=pat\+\+: a textual defense of VLMs .* use it with "
                                         r"model=vlm/<backend>"):
        build_defense(compose_defense("pat++", tmp_path))


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_each_defense_instantiates_and_trains_a_step(name, tmp_path):
    cfg = compose_defense(name, tmp_path)
    parts = build_defense(cfg)
    n_transforms, mixer_type, callback_type = EXPECTED[name]
    assert len(parts["transforms"]) == n_transforms
    assert parts["mixer"] is None if mixer_type is None else isinstance(parts["mixer"], mixer_type)
    assert parts["callback"] is None if callback_type is None else isinstance(parts["callback"], callback_type)
    if name == "cutout":
        assert isinstance(parts["transforms"][0], LaneCutout)
    if name.startswith("aam"):
        assert parts["callback"].mode == name and parts["callback"].layer == "backbone"
        assert (parts["callback"].t_haa, parts["callback"].t_laa, parts["callback"].beta) == (0.6, 0.4, 0.5)
    train(cfg)
    ckpt = torch.load(tmp_path / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert ckpt["global_step"] == 2


def test_an_unknown_defense_key_is_named(tmp_path):
    cfg = compose_defense("none", tmp_path, ["+defense.callbacks=[]"])
    with pytest.raises(ValueError, match="callbacks"):
        build_defense(cfg)


def test_data_train_transforms_run_before_the_defense_transforms(tmp_path):
    from lanevil_train.illusions import IllusionTransform
    from lanevil_train.tasks.builders import build_datamodule, build_model, model_config

    cfg = compose_defense("cutout", tmp_path,
                          ["data.train_transforms=[{_target_: lanevil_train.illusions.IllusionTransform, p: 1.0}]"])
    model = build_model(model_config(cfg))
    datamodule = build_datamodule(cfg, ("train",), model, build_defense(cfg))
    steps = [type(t) for t in datamodule.train_processor.pipeline.transforms]
    assert steps.index(IllusionTransform) < steps.index(LaneCutout) < len(steps) - 1  # both before the resize
    assert not any(t is IllusionTransform for t in map(type, datamodule.eval_processor.pipeline.transforms))
