"""task=profile: parameters, FLOPs, latency and memory of a config's or a checkpoint's network, and of every family;
the counts are checked against the built model and a hand count, bad settings refused by the config check."""

from __future__ import annotations

import json

import pytest
import torch
from torch import nn

from lanevil_train.models.profile import count_flops, count_parameters, markdown_table, profile_network
from lanevil_train.tasks.builders import build_model, model_config
from lanevil_train.tasks.config_check import ConfigError, check_config
from tests.tasks.cli_helpers import composed, run_in_process

QUICK = ["task=profile", "task.runs=1", "task.warmup=0", "trainer.accelerator=cpu", "progress=none"]


def _read(run_dir):
    assert not list(run_dir.glob(".*partial"))  # written atomically
    assert (run_dir / "profile.md").read_text().startswith("# Profile\n")
    return json.loads((run_dir / "profile.json").read_text())


def test_a_configs_profile_counts_the_built_models_parameters(tmp_path):
    args = [*QUICK, "model=laneatt", "data.input_size=[64,128]", "task.batch_size=2"]
    fps = run_in_process(args, tmp_path)
    [row] = _read(tmp_path)["rows"]
    torch.manual_seed(0)
    model = build_model(model_config(composed(args)))
    assert row["parameters"] == {"total": sum(p.numel() for p in model.parameters()),
                                 "trainable": sum(p.numel() for p in model.parameters() if p.requires_grad)}
    assert row["label"] == "laneatt-resnet18" and row["input_size"] == [64, 128] and row["device"].startswith("cpu")
    assert row["flops"] > 0 and row["macs"] == row["flops"] / 2 and sum(row["by_part"].values()) == row["flops"]
    assert [b["batch"] for b in row["batches"]] == [1, 2]
    for b in row["batches"]:
        assert b["forward_ms"] > 0 and b["forward_decode_ms"] > 0 and b["peak_memory_bytes"] >= 0
        assert b["forward_fps"] == pytest.approx(b["batch"] * 1e3 / b["forward_ms"])
    assert fps == row["batches"][0]["forward_fps"]
    assert "| laneatt-resnet18 | 64x128 |" in (tmp_path / "profile.md").read_text()


def test_a_checkpoint_is_profiled_as_its_own_network(tmp_path):
    torch.manual_seed(0)
    model = build_model(model_config(composed(["model=bezierlanenet", "data.input_size=[64,128]"])))
    ckpt = tmp_path / "model.ckpt"
    torch.save({"state_dict": model.state_dict(), "lanevil_model": model.build_config}, ckpt)
    # the command line's model and size are not the checkpoint's: the checkpoint's network is measured
    run_in_process([*QUICK, f"ckpt_path={ckpt}", "model=clrnet", "task.batch_size=1"], tmp_path / "run")
    [row] = _read(tmp_path / "run")["rows"]
    assert row["label"] == "bezierlanenet-resnet18" and row["input_size"] == [64, 128]
    assert row["checkpoint"] == str(ckpt) and [b["batch"] for b in row["batches"]] == [1]
    assert row["parameters"]["total"] == sum(p.numel() for p in model.parameters())


def test_flops_of_a_known_network_equal_the_hand_count():
    conv = nn.Conv2d(3, 8, 3, padding=1)  # 8 x 3 x 3 x 3 multiply-adds per output pixel, 16 x 20 pixels
    net = nn.Sequential(conv, nn.ReLU(), nn.Flatten(), nn.Linear(8 * 16 * 20, 5))
    counted = count_flops(net, (16, 20))
    conv_macs, linear_macs = 8 * 3 * 3 * 3 * 16 * 20, 8 * 16 * 20 * 5
    assert counted["flops"] == 2 * (conv_macs + linear_macs)  # torch's convention: 2 FLOPs per multiply-add
    assert counted["macs"] == conv_macs + linear_macs
    assert counted["by_part"] == {"0": 2 * conv_macs, "3": 2 * linear_macs} and counted["uncounted"] == []
    conv.weight.requires_grad_(False)
    assert count_parameters(net) == {"total": 8 * 27 + 8 + 2560 * 5 + 5, "trainable": 8 + 2560 * 5 + 5}
    assert conv.bias.requires_grad and not conv.weight.requires_grad  # left as they were

    row = profile_network(net, (16, 20), "cpu", batch_sizes=(1, 3), warmup=0, runs=2)
    assert row["flops"] == counted["flops"] and [b["batch"] for b in row["batches"]] == [1, 3]
    assert "forward_decode_ms" not in row["batches"][0]  # a plain network has no decoding
    assert "| model | 16x20 | 0.01 M (0.01) | 0.00 | 0.00 |" in markdown_table([row])


def test_families_all_profiles_every_detector_family(tmp_path):
    run_in_process([*QUICK, "task.families=all", "task.input_size=[32,224]", "task.batch_size=1"], tmp_path)
    rows = _read(tmp_path)["rows"]
    assert [row["family"] for row in rows] == ["bezierlanenet", "clrernet", "clrnet", "ganet", "laneatt", "laneformer",
                                               "scnn", "ufld"]
    assert all(row["input_size"] == [32, 224] and row["flops"] > 0 for row in rows)
    assert {row["label"] for row in rows} >= {"scnn-vgg16_bn", "clrnet-resnet18"}  # their paper's backbones
    table = (tmp_path / "profile.md").read_text()
    assert all(f"| {row['label']} | 32x224 |" in table for row in rows)


def _problems(*overrides: str) -> list[str]:
    try:
        check_config(composed(list(overrides)))
    except ConfigError as error:
        return error.problems
    return []


def test_bad_settings_are_refused_naming_the_key():
    assert _problems("task=profile", "task.runs=0") == ["task.runs: expected null or an integer >= 1, got 0"]
    assert _problems("task=profile", "task.warmup=-1")[0].startswith("task.warmup: expected null or an integer >= 0")
    assert _problems("task=profile", "task.batch_size=0")[0].startswith("task.batch_size: expected an integer >= 1")
    [bad] = _problems("task=profile", "task.families=[clrnet,yolo]")
    assert bad.startswith("task.families: expected null or all or a list of detector families") and "'yolo'" in bad
    assert _problems("task=report", "task.runs=[a,b]") == []  # task.runs is another task's list of folders
    vlm = _problems("task=profile", "model=vlm/embedded")
    assert any(p.startswith("model.kind: expected detector (task=profile measures lane detectors: model=laneatt")
               and "model=vlm/<backend> is a VLM), got 'vlm'" in p for p in vlm), vlm
    # a published file's experiment: the network only, no dataset folder needed
    assert _problems("task=profile", "experiment=official_clrnet_culane") == []
