"""Weight files cut short (a download that stopped) in a model folder, a sharded model or an adapter folder: refused
before anything loads, naming the option, the folder, the file and the sizes."""

from __future__ import annotations

import shutil

import pytest
import torch

from lanevil_train.vlm.backends.hf import HFVLM
from lanevil_train.vlm.backends.weight_files import check_weight_files
from lanevil_train.vlm.training.finetune import VLMFineTuner


def cut(path, keep: int) -> tuple[int, int]:
    """Truncate `path` to `keep` bytes; (size before, size after)."""
    data = path.read_bytes()
    path.write_bytes(data[:keep])
    return len(data), keep


def test_a_truncated_model_file_is_named_with_the_size_its_header_promises(tiny_vlm_dir, tmp_path):
    model = shutil.copytree(tiny_vlm_dir("qwen2_vl"), tmp_path / "model")
    check_weight_files(model, "model.path")  # whole: nothing to say
    whole, kept = cut(model / "model.safetensors", (model / "model.safetensors").stat().st_size // 2)
    with pytest.raises(ValueError) as caught:
        HFVLM(model, device="cpu")
    assert str(caught.value) == (f"model.path {model}: model.safetensors is truncated: header says {whole} bytes, "
                                 f"file has {kept} (a download or copy that stopped?); fetch or save it again")
    cut(model / "model.safetensors", 100)  # the header's JSON itself is cut
    with pytest.raises(ValueError, match=r"model.safetensors is truncated: header says its JSON alone takes \d+ "
                                         r"bytes, file has 100"):
        HFVLM(model, device="cpu")
    cut(model / "model.safetensors", 5)
    with pytest.raises(ValueError, match="truncated: 5 bytes, shorter than the 8-byte header length"):
        HFVLM(model, device="cpu")


def test_a_sharded_model_has_every_shard_and_each_whole(tiny_vlm_dir, tmp_path):
    source = tiny_vlm_dir("qwen2_vl")
    sharded = shutil.copytree(source, tmp_path / "sharded", ignore=shutil.ignore_patterns("model.safetensors"))
    HFVLM(source, device="cpu", dtype="float32").model.save_pretrained(sharded, max_shard_size="300KB")
    shards = sorted(p.name for p in sharded.glob("model-*-of-*.safetensors"))
    assert len(shards) >= 2 and (sharded / "model.safetensors.index.json").is_file()
    HFVLM(sharded, device="cpu")  # a whole sharded model loads
    last = sharded / shards[-1]
    whole, kept = cut(last, last.stat().st_size - 64)
    with pytest.raises(ValueError, match=rf"^model.path {sharded}: {shards[-1]} is truncated: header says {whole} "
                                         rf"bytes, file has {kept} "):
        HFVLM(sharded, device="cpu")
    last.unlink()
    with pytest.raises(FileNotFoundError, match=rf"^model.path {sharded}: {shards[-1]}, a shard "
                                                r"model.safetensors.index.json lists, is missing"):
        HFVLM(sharded, device="cpu")


def test_a_truncated_adapter_and_a_truncated_bin_file_are_named(tiny_vlm_dir, tmp_path):
    base = tiny_vlm_dir("qwen2_vl")
    adapter = VLMFineTuner(str(base), lora={"r": 4, "alpha": 8, "dropout": 0.0}).save_model(tmp_path / "adapter")
    weights = adapter / "adapter_model.safetensors"
    whole, kept = cut(weights, weights.stat().st_size - 10)
    with pytest.raises(ValueError, match=rf"^model.adapter {adapter}: adapter_model.safetensors is truncated: header "
                                         rf"says {whole} bytes, file has {kept} "):
        HFVLM(base, device="cpu", adapter=adapter)
    weights.unlink()
    torch.save({"w": torch.zeros(64)}, adapter / "adapter_model.bin")
    size = (adapter / "adapter_model.bin").stat().st_size
    cut(adapter / "adapter_model.bin", size // 2)
    with pytest.raises(ValueError, match=rf"^model.adapter {adapter}: adapter_model.bin is truncated: {size // 2} "
                                         r"bytes, a torch archive whose end is missing"):
        check_weight_files(adapter, "model.adapter")
