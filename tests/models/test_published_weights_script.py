"""benchmarks/published_weights.py: each official file in a folder recognised and given the project's own evaluation
commands for its release (here --dry-run, on files with the official keys and shapes and no real weights)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import torch

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "published_weights.py"
_spec = importlib.util.spec_from_file_location("published_weights", SCRIPT)
script = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(script)


def _resnet18_keys(prefix: str, stages: list[str]) -> dict:
    return {f"{prefix}{stage}.{block}.conv1.weight": torch.zeros(1) for stage in stages for block in (0, 1)}


def test_each_file_gets_its_releases_clean_and_suite_commands(tmp_path, capsys):
    weights = tmp_path / "weights"
    (weights / "laneatt_r18_culane" / "models").mkdir(parents=True)
    ufld = {"model.conv1.weight": torch.zeros(1), "pool.weight": torch.zeros(1), "cls.0.weight": torch.zeros(1),
            "cls.2.weight": torch.zeros(101 * 56 * 4, 1),
            **_resnet18_keys("model.", ["layer1", "layer2", "layer3", "layer4"])}
    torch.save({"model": ufld}, weights / "tusimple_18.pth")
    laneatt = {"feature_extractor.0.weight": torch.zeros(1), "conv1.weight": torch.zeros(64, 1),
               "attention_layer.weight": torch.zeros(999, 64 * 11), "cls_layer.weight": torch.zeros(1),
               **_resnet18_keys("feature_extractor.", ["4", "5", "6", "7"])}
    torch.save({"epoch": 100, "model": laneatt}, weights / "laneatt_r18_culane" / "models" / "model_0100.pt")
    (weights / "laneatt_r18_llamas" / "models").mkdir(parents=True)
    torch.save({"epoch": 100, "model": laneatt}, weights / "laneatt_r18_llamas" / "models" / "model_0100.pt")
    torch.save({"net": {"x": torch.zeros(1)}}, weights / "other.pth")

    script.main(["--weights", str(weights), "--tusimple", "/data/tusimple", "--culane", "/data/culane",
                 "--llamas", "/data/llamas", "--laneatt-data", "/src/LaneATT/data", "--out", str(tmp_path / "runs"),
                 "--dry-run"])
    lines = capsys.readouterr().out.splitlines()
    assert any(line.startswith("skipped") and "other.pth" in line for line in lines)
    runs = [line for line in lines if "-m lanevil_train" in line]
    assert len(runs) == 6  # clean and suite of each file
    laneatt_clean, laneatt_suite, llamas_clean, llamas_suite, ufld_clean, ufld_suite = runs
    assert "experiment=official_laneatt_llamas backbone=resnet18" in llamas_clean
    assert "data.root=/data/llamas" in llamas_clean
    assert "model.head.anchor_frequency_file=/src/LaneATT/data/llamas_anchors_freq.pt" in llamas_suite
    assert "experiment=official_ufld_tusimple backbone=resnet18" in ufld_clean
    assert "data.root=/data/tusimple" in ufld_clean and "task.predictions=true" in ufld_clean
    assert "task.suite=synthetic" in ufld_suite
    assert "experiment=official_laneatt_culane backbone=resnet18" in laneatt_clean
    assert "model.head.anchor_frequency_file=/src/LaneATT/data/culane_anchors_freq.pt" in laneatt_suite


def _scnn_vgg(classes: int, exist_inputs: int) -> dict:
    """pytorch-auto-drive's DeepLabV1 SCNN keys, with the two shapes that tell its release."""
    return {"encoder.net.0.weight": torch.zeros(1), "fc67.0.weight": torch.zeros(1), "scnn.conv_d.weight":
            torch.zeros(1), "fc8.1.weight": torch.zeros(classes, 128, 1, 1),
            "lane_classifier.linear1.weight": torch.zeros(128, exist_inputs)}


def test_scnn_files_get_their_commands_and_the_others_are_skipped_saying_why(tmp_path, capsys):
    weights = tmp_path / "weights"
    weights.mkdir()
    torch.save({"model": _scnn_vgg(7, 6160), "optimizer": None, "lr_scheduler": None}, weights / "vgg16_tusimple.pt")
    torch.save({"model": _scnn_vgg(5, 4400)}, weights / "vgg16_llamas.pt")
    resnet = {"backbone.conv1.weight": torch.zeros(1), "channel_reducer.conv1.weight": torch.zeros(1),
              "scnn_layer.conv_d.weight": torch.zeros(1), "classifier.0.conv.weight": torch.zeros(5, 128, 3, 3),
              **_resnet18_keys("backbone.", ["layer1", "layer2", "layer3", "layer4"])}
    torch.save({"model": resnet}, weights / "resnet18_culane.pt")

    script.main(["--weights", str(weights), "--tusimple", "/data/tusimple", "--culane", "/data/culane",
                 "--out", str(tmp_path / "runs"), "--dry-run"])
    lines = capsys.readouterr().out.splitlines()
    runs = [line for line in lines if "-m lanevil_train" in line]
    assert len(runs) == 2 and "experiment=official_scnn_tusimple backbone=vgg16_bn" in runs[0]
    skipped = {line.split(":", 1)[0].rsplit("/", 1)[-1]: line for line in lines if line.startswith("skipped")}
    assert "that this project cannot load: its network is not this project's SCNN" in skipped["resnet18_culane.pt"]
    assert "the llamas release" in skipped["vgg16_llamas.pt"] and "no dataset this benchmark scores" in \
        skipped["vgg16_llamas.pt"]


def _bezierlanenet(depth_blocks: tuple[int, int, int], head_layers: int = 2) -> dict:
    """pytorch-auto-drive's BezierLaneNet keys (the ResNet up to layer3), the same shapes for every dataset."""
    state = {"backbone.conv1.weight": torch.zeros(1), "simple_flip_2d.proj1.0.weight": torch.zeros(1),
             "simple_flip_2d.proj2_conv.weight": torch.zeros(1), "proj_classification.weight": torch.zeros(1, 256, 1),
             "proj_regression.weight": torch.zeros(8, 256, 1)}
    for stage, blocks in zip(("layer1", "layer2", "layer3"), depth_blocks):
        state.update({f"backbone.{stage}.{b}.conv1.weight": torch.zeros(1) for b in range(blocks)})
    state.update({f"regression_head.hidden_layers.{i}.weight": torch.zeros(256, 256, 3) for i in range(head_layers)})
    state.update({f"dilated_blocks.{i}.conv1.0.weight": torch.zeros(64, 256, 1, 1) for i in range(2)})
    return state


def test_bezierlanenet_files_get_the_commands_of_the_dataset_their_path_names(tmp_path, capsys):
    weights = tmp_path / "weights"
    for folder, blocks, layers in (("resnet34_bezierlanenet_culane-aug2", (3, 4, 6), 2),
                                   ("resnet18_bezierlanenet_tusimple-aug2", (2, 2, 2), 2),
                                   ("resnet18_bezierlanenet-aug2_llamas", (2, 2, 2), 2),
                                   ("resnet18_bezierlanenet_culane-1layer", (2, 2, 2), 1)):
        (weights / folder).mkdir(parents=True)
        torch.save({"model": _bezierlanenet(blocks, layers), "optimizer": None, "lr_scheduler": None},
                   weights / folder / "model.pt")

    script.main(["--weights", str(weights), "--tusimple", "/data/tusimple", "--culane", "/data/culane",
                 "--out", str(tmp_path / "runs"), "--dry-run"])
    lines = capsys.readouterr().out.splitlines()
    runs = [line for line in lines if "-m lanevil_train" in line]
    assert len(runs) == 4  # clean and suite of each file, in the order of their paths
    tusimple_clean, _, culane_clean, _ = runs
    assert "experiment=official_bezierlanenet_culane backbone=resnet34" in culane_clean
    assert "data.root=/data/culane" in culane_clean and "task.label=bezierlanenet-resnet34-culane" in culane_clean
    assert "experiment=official_bezierlanenet_tusimple backbone=resnet18" in tusimple_clean
    skipped = [line for line in lines if line.startswith("skipped")]
    assert len(skipped) == 2
    assert any("aug2_llamas" in line and "of LLAMAS (its path says so)" in line for line in skipped)
    assert any("culane-1layer" in line and "of no published release" in line
               and "model.head.projection_layers=1" in line for line in skipped)
    assert script.PUBLISHED[("bezierlanenet", "culane", "resnet34")] == ("CULane_F1", 75.57)


def _ganet(depth: int, levels: int, points: int, attention: int | None) -> dict:
    """Wolfwjs/GANet's keys (mmcv's 'state_dict'), with the shapes that tell its release: the ResNet's blocks, the
    FPN levels, the LFA's points and the attention's width."""
    blocks = {18: (2, 2, 2, 2), 101: (3, 4, 23, 3)}[depth]
    state = {f"backbone.layer{i + 1}.{b}.conv{'3' if depth > 34 else '1'}.weight": torch.zeros(1)
             for i, n in enumerate(blocks) for b in range(n)}
    state.update({"backbone.conv1.weight": torch.zeros(1), "neck.fpn_convs.0.conv.weight": torch.zeros(1),
                  "neck.def_convs.0.reppoints_cls_conv.weight": torch.zeros(64, 256, 1, points),
                  "bbox_head.keypts_head.hm.0.weight": torch.zeros(1),
                  "bbox_head.offset_head.offset_map.0.weight": torch.zeros(1),
                  "bbox_head.reg_head.offset_map.0.weight": torch.zeros(1),
                  **{f"neck.lateral_convs.{i}.conv.weight": torch.zeros(64, 1, 1, 1) for i in range(levels)}})
    if attention:
        state.update({f"neck.trans_head.attn_layers.{i}.pre_conv.conv.weight": torch.zeros(attention, 1, 3, 3)
                      for i in range(2)})
    return state


def test_ganet_files_get_their_releases_commands_the_dataset_from_their_names(tmp_path, capsys):
    weights = tmp_path / "weights"
    weights.mkdir()
    meta = {"mmdet_version": "2.0.0", "config": "...", "CLASSES": None}
    torch.save({"meta": meta, "state_dict": _ganet(18, 3, 7, 64), "optimizer": {}},
               weights / "ganet_culane_resnet18.pth")
    torch.save({"meta": meta, "state_dict": _ganet(101, 4, 9, 256)}, weights / "ganet_tusimple_resnet101.pth")
    torch.save({"meta": meta, "state_dict": _ganet(18, 3, 7, None)}, weights / "ganet_culane_plain.pth")

    script.main(["--weights", str(weights), "--tusimple", "/data/tusimple", "--culane", "/data/culane",
                 "--out", str(tmp_path / "runs"), "--dry-run"])
    lines = capsys.readouterr().out.splitlines()
    runs = [line for line in lines if "-m lanevil_train" in line]
    assert len(runs) == 4  # clean and suite of the two releases
    culane_clean, _, tusimple_clean, tusimple_suite = runs
    assert "experiment=official_ganet_culane backbone=resnet18" in culane_clean
    assert "data.root=/data/culane" in culane_clean and "task.label=ganet-resnet18-culane" in culane_clean
    assert "experiment=official_ganet_large_tusimple backbone=resnet101" in tusimple_clean
    assert "data.root=/data/tusimple" in tusimple_suite and "task.suite=synthetic" in tusimple_suite
    skipped = [line for line in lines if line.startswith("skipped")]
    assert len(skipped) == 1 and "ganet_culane_plain.pth" in skipped[0] and "an unpublished setting" in skipped[0]
    assert script.PUBLISHED[("ganet", "tusimple", "resnet18")] == ("F1", 97.71)
    assert script.PUBLISHED[("ganet", "culane", "resnet101")] == ("CULane_F1", 79.63)
