"""trainer=fsdp: the FSDP units are each family's blocks, and 2 CPU processes (gloo) train a tiny VLM, checkpoint and
resume; trainer=deepspeed composes into Lightning's ZeRO strategy (DeepSpeed itself needs CUDA GPUs).

Run as a script (`python tests/vlm/test_sharding.py MODEL_DIR OUT MAX_STEPS [LORA]`) this file is one rank of the
2-process FSDP run: Lightning relaunches it as rank 1, exactly as it relaunches `python -m lanevil_train`.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from lanevil_dev.tiny_vlm import FAMILIES, make_tiny_vlm
from lanevil_train.vlm.training.sharding import (
    LayerWrapFSDPStrategy,
    checkpointed_blocks,
    fsdp_units,
    gathered_state_dict,
    layer_classes,
    layer_wrap_policy,
    repeated_block_classes,
)

REPO = Path(__file__).resolve().parents[2]
QA = [("How many lanes does the road have?", "The road has three lanes."), ("Is it wet?", "Yes."),
      ("What should the ego vehicle do next?", "Keep the lane."), ("Is there a crack ahead?", "No.")]
LORA = {"r": 4, "alpha": 8, "dropout": 0.0}
# The blocks each tiny family's FSDP units must be: its language decoder layers and its vision tower blocks.
BLOCKS = {
    "llava": {"LlamaDecoderLayer", "CLIPEncoderLayer"},
    "llava_onevision": {"Qwen2DecoderLayer", "SiglipEncoderLayer"},
    "qwen2_vl": {"Qwen2VLDecoderLayer", "Qwen2VLVisionBlock"},
    "qwen2_5_vl": {"Qwen2_5_VLDecoderLayer", "Qwen2_5_VLVisionBlock"},
    "idefics3": {"LlamaDecoderLayer", "Idefics3EncoderLayer"},
    "smolvlm": {"LlamaDecoderLayer", "SmolVLMEncoderLayer"},
}


def _items() -> list[dict]:
    """Four (clip, question, answer) items of random 32x48 frames, fixed by seed."""
    rng = np.random.default_rng(3)
    return [{"frames": rng.integers(0, 256, (6, 32, 48, 3), dtype=np.uint8), "question": q, "answer": a,
             "key": f"c{i}/q{i}", "meta": {"clip_id": f"c{i}"}} for i, (q, a) in enumerate(QA)]


# ---- the auto-wrap policy on each family's module tree ---------------------------------------------------------

@pytest.mark.parametrize("family", FAMILIES)
def test_the_blocks_found_are_the_decoder_layers_and_vision_blocks_of_each_family(family):
    model, _ = make_tiny_vlm(family)
    assert {cls.__name__ for cls in repeated_block_classes(model)} == BLOCKS[family]
    policy = layer_wrap_policy(model)
    assert {cls.__name__ for cls in policy._module_classes} == BLOCKS[family]


@pytest.fixture
def one_process_group(tmp_path):
    """A 1-process gloo group, so FSDP can wrap a model in this process (destroyed after the test)."""
    import torch.distributed as dist

    dist.init_process_group("gloo", init_method=f"file://{tmp_path / 'store'}", rank=0, world_size=1)
    yield
    dist.destroy_process_group()


@pytest.mark.parametrize("family", ["llava", "qwen2_5_vl", "idefics3"])
def test_fsdp_makes_one_unit_per_block_and_keeps_the_rest_in_the_root(family, one_process_group):
    from torch.distributed.fsdp import FullyShardedDataParallel

    model, _ = make_tiny_vlm(family)
    wrapped = FullyShardedDataParallel(model, auto_wrap_policy=layer_wrap_policy(model),
                                       device_id=torch.device("cpu"), use_orig_params=True)
    expected = {name: 2 for name in BLOCKS[family]}  # 2 decoder layers, 2 vision blocks in every tiny model
    assert fsdp_units(wrapped) == {type(model).__name__: 1, **expected}


def test_named_layer_classes_override_and_errors_name_the_input():
    model, _ = make_tiny_vlm("llava")
    assert {cls.__name__ for cls in layer_classes(model, ["LlamaDecoderLayer"])} == {"LlamaDecoderLayer"}
    with pytest.raises(ValueError, match=r"layer_classes: \['GPTBlock'\] are not module classes.*CLIPEncoderLayer"):
        layer_classes(model, ["GPTBlock"])
    with pytest.raises(ValueError, match="no repeated transformer blocks found in Sequential.*layer_classes"):
        layer_classes(nn.Sequential(nn.Linear(2, 2), nn.ReLU()))
    mixed = nn.ModuleList([nn.Linear(2, 2), nn.Conv1d(2, 2, 1)])  # not one class: not a block list
    assert repeated_block_classes(nn.ModuleDict({"m": mixed})) == set()


@pytest.mark.parametrize("kwargs, message", [
    ({"sharding_strategy": "FULL"}, "sharding_strategy: expected one of FULL_SHARD"),
    ({"state_dict_type": "single"}, "state_dict_type: expected one of full, sharded, got 'single'"),
    ({"layer_classes": "LlamaDecoderLayer"}, "layer_classes: expected null or a list of class names"),
    ({"checkpoint_activations": "yes"}, "checkpoint_activations: expected true or false"),
])
def test_bad_strategy_settings_are_refused_naming_the_argument(kwargs, message):
    with pytest.raises(ValueError, match=message):
        LayerWrapFSDPStrategy(**kwargs)


# ---- the configs --------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def compose_root():
    from hydra import compose, initialize_config_module

    with initialize_config_module(config_module="lanevil_train.conf", version_base="1.3"):
        yield lambda *overrides: compose(config_name="config", overrides=["output_dir=unused", "logger=none",
                                                                          "progress=none", *overrides])


def test_trainer_fsdp_builds_the_layer_wrap_strategy_full_shard_bf16(compose_root):
    from torch.distributed.fsdp import ShardingStrategy

    from lanevil_train.tasks.builders import build_trainer

    trainer = build_trainer(compose_root("trainer=fsdp", "trainer.accelerator=cpu"), logger=False)
    strategy = trainer.strategy
    assert isinstance(strategy, LayerWrapFSDPStrategy)
    assert strategy.sharding_strategy == ShardingStrategy.FULL_SHARD and strategy._state_dict_type == "full"
    assert strategy.kwargs["use_orig_params"] is True and not strategy.checkpoint_activations
    assert strategy.precision_plugin.precision == "bf16-mixed"
    tuned = build_trainer(compose_root("trainer=fsdp", "trainer.accelerator=cpu", "trainer.precision=32-true",
                                       "trainer.strategy.sharding_strategy=SHARD_GRAD_OP",
                                       "trainer.strategy.checkpoint_activations=true",
                                       "trainer.strategy.layer_classes=[LlamaDecoderLayer]"), logger=False)
    assert tuned.strategy.sharding_strategy == ShardingStrategy.SHARD_GRAD_OP
    assert tuned.strategy.checkpoint_activations and tuned.strategy.layer_class_names == ["LlamaDecoderLayer"]
    with pytest.raises(ValueError, match="trainer.strategy.*sharding_strategy: expected one of"):
        build_trainer(compose_root("trainer=fsdp", "trainer.strategy.sharding_strategy=ALL"), logger=False)


def test_merging_lora_under_fsdp_is_refused_before_training_and_merging_elsewhere_is_not(compose_root):
    from lanevil_train.tasks.vlm.train import check_sharded_merge

    lora = ["model=vlm/hf", "model.path=unused"]  # model=vlm/hf trains LoRA by default
    with pytest.raises(ValueError, match=r"model.merge_adapter: true cannot merge under trainer=fsdp .* "
                                         r"model.adapter=RUN/model model.merge_adapter=true"):
        check_sharded_merge(compose_root("trainer=fsdp", *lora, "model.merge_adapter=true"))
    check_sharded_merge(compose_root("trainer=fsdp", *lora))  # the adapter saves unmerged: allowed
    check_sharded_merge(compose_root("trainer=cpu", *lora, "model.merge_adapter=true"))


def test_trainer_deepspeed_composes_into_lightnings_zero_strategy(compose_root):
    pytest.importorskip("deepspeed", reason="trainer=deepspeed needs the deepspeed package")
    from pytorch_lightning.strategies import DeepSpeedStrategy

    from lanevil_train.tasks.builders import instantiate_at

    cfg = compose_root("trainer=deepspeed")
    assert cfg.trainer.accelerator == "gpu" and cfg.trainer.precision == "bf16-mixed"
    strategy = instantiate_at(cfg.trainer.strategy, "trainer.strategy")
    assert isinstance(strategy, DeepSpeedStrategy)
    zero = strategy.config["zero_optimization"]
    assert zero["stage"] == 2 and "offload_optimizer" not in zero and "offload_param" not in zero
    cfg = compose_root("trainer=deepspeed", "trainer.strategy.stage=3", "trainer.strategy.offload_optimizer=true")
    zero = instantiate_at(cfg.trainer.strategy, "trainer.strategy").config["zero_optimization"]
    assert zero["stage"] == 3 and zero["offload_optimizer"]["device"] == "cpu" and "offload_param" not in zero
    with pytest.raises(ValueError, match=r"trainer.strategy.stage: expected 1, 2 or 3 \(ZeRO stage\), got 4"):
        instantiate_at(compose_root("trainer=deepspeed", "trainer.strategy.stage=4").trainer.strategy,
                       "trainer.strategy")


# ---- 2 CPU processes: train, checkpoint, resume ----------------------------------------------------------------

def _run_ranks(model_dir: Path, out: Path, max_steps: int, lora: bool = False) -> None:
    """This file as a script: 2 FSDP ranks on CPU (Lightning relaunches rank 1), `max_steps` steps into `out`."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, __file__, str(model_dir), str(out), str(max_steps), *(["lora"] if lora else [])]
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, f"{' '.join(cmd)} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-6000:]}"


def _losses(out: Path, rank: int) -> dict[int, float]:
    """global step -> training loss of `rank`'s batch at that step, as the script recorded them."""
    lines = (out / f"loss{rank}.txt").read_text().split()
    return {int(step): float(loss) for step, loss in zip(lines[0::2], lines[1::2])}


@pytest.mark.parametrize("lora", [False, pytest.param(True, marks=pytest.mark.slow)], ids=["full", "lora"])
def test_two_cpu_processes_train_checkpoint_and_resume_under_fsdp(tiny_vlm_dir, tmp_path, lora):
    """4 steps on 2 gloo ranks (each its own 2 samples; full fine-tuning with activation checkpointing, LoRA
    without) lower each rank's loss; last.ckpt holds the trainable
    weights under their plain names and, loaded without FSDP, gives the loss rank 0 then sees at resumed step 4;
    the model (or LoRA adapter) rank 0 saves from the gathered state dict holds those same weights."""
    from lanevil_train.vlm.backends.hf import HFVLM
    from lanevil_train.vlm.training.finetune import VLMFineTuner, collate_clip_qa

    model_dir = tiny_vlm_dir("qwen2_vl")
    _run_ranks(model_dir, tmp_path, 4, lora)
    units = json.loads((tmp_path / "units.json").read_text())
    assert units["fsdp"] == {"VLMFineTuner": 1, "Qwen2VLDecoderLayer": 2, "Qwen2VLVisionBlock": 2}
    blocks = {"Qwen2VLDecoderLayer": 2, "Qwen2VLVisionBlock": 2}  # full fine-tuning runs with checkpointing on
    assert units["checkpointed"] == ({} if lora else blocks)
    for rank in (0, 1):  # steps 0-1 and 2-3 are two epochs over the same 2 samples of the rank
        losses = _losses(tmp_path, rank)
        assert sorted(losses) == [0, 1, 2, 3]
        assert losses[2] + losses[3] < losses[0] + losses[1] - 0.1, losses
    saved = torch.load(tmp_path / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert saved["global_step"] == 4
    plain = VLMFineTuner(str(model_dir), lora=LORA if lora else None)
    assert set(saved["state_dict"]) == plain.trainable_keys()
    plain.load_state_dict(saved["state_dict"], strict=False)
    plain.train()
    resumed_loss = plain.batch_loss(collate_clip_qa([_items()[0]])).item()
    sample = _items()[0]
    if lora:  # the adapter in peft's format, loaded onto the base model
        saved_vlm = HFVLM(model_dir, adapter=tmp_path / "model", dtype="float32", device="cpu")
    else:
        saved_vlm = HFVLM(tmp_path / "model", dtype="float32", device="cpu")
    plain_vlm = HFVLM.wrap(plain.model, plain.processor, model_dir)
    loss_of = [vlm.answer_loss([list(sample["frames"])], [sample["question"]], [sample["answer"]]).item()
               for vlm in (saved_vlm, plain_vlm)]
    assert abs(loss_of[0] - loss_of[1]) < 1e-5, loss_of  # what rank 0 saved from the gathered weights is whole
    base_loss = HFVLM(model_dir, dtype="float32", device="cpu").answer_loss(
        [list(sample["frames"])], [sample["question"]], [sample["answer"]]).item()
    assert abs(loss_of[0] - base_loss) > 1e-3, (loss_of, base_loss)  # and it is the trained one, not the base
    _run_ranks(model_dir, tmp_path, 6, lora)  # resumes from last.ckpt
    assert torch.load(tmp_path / "checkpoints" / "last.ckpt", map_location="cpu",
                      weights_only=False)["global_step"] == 6
    after = _losses(tmp_path, 0)
    assert sorted(after) == [0, 1, 2, 3, 4, 5]  # resumed at step 4, not from 0
    assert abs(after[4] - resumed_loss) < 1e-4, (after[4], resumed_loss)  # rank 0's sample 0, restored weights


def _rank_main(model_dir: str, out: str, max_steps: int, lora: bool) -> None:
    """One rank of the 2-process FSDP run: trainer=fsdp composed and built as task=train builds it."""
    import pytorch_lightning as pl
    from hydra import compose, initialize_config_module
    from pytorch_lightning.callbacks import ModelCheckpoint
    from torch.utils.data import DataLoader

    from lanevil_train.tasks.builders import build_trainer
    from lanevil_train.vlm.training.finetune import VLMFineTuner, collate_clip_qa

    class Record(pl.Callback):
        def on_fit_start(self, trainer, module):
            if trainer.global_rank == 0:
                units = {"fsdp": fsdp_units(trainer.model), "checkpointed": checkpointed_blocks(trainer.model)}
                Path(out, "units.json").write_text(json.dumps(units))

        def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx):
            with open(Path(out, f"loss{trainer.global_rank}.txt"), "a") as handle:
                handle.write(f"{trainer.global_step - 1} {float(outputs['loss']):.7f}\n")

    with initialize_config_module(config_module="lanevil_train.conf", version_base="1.3"):
        cfg = compose(config_name="config", overrides=[
            "trainer=fsdp", "trainer.accelerator=cpu", "trainer.devices=2", "trainer.precision=32-true",
            f"trainer.max_steps={max_steps}", "logger=none", "progress=none", f"output_dir={out}",
            f"trainer.strategy.checkpoint_activations={str(not lora).lower()}",
            "+trainer.enable_model_summary=false"])
    checkpoints = Path(out, "checkpoints")
    last = checkpoints / "last.ckpt"
    ckpt_path = str(last) if last.exists() else None
    trainer = build_trainer(cfg, callbacks=[Record(), ModelCheckpoint(dirpath=checkpoints, save_last=True)],
                            logger=False)
    torch.manual_seed(0)
    module = VLMFineTuner(model_dir, lora=LORA if lora else None, lr=1e-2 if lora else 3e-3)
    loader = DataLoader(_items(), batch_size=1, shuffle=False, collate_fn=collate_clip_qa)
    trainer.fit(module, loader, ckpt_path=ckpt_path)
    state = gathered_state_dict(trainer)  # every rank takes part; rank 0 saves the whole model (or adapter)
    if trainer.is_global_zero:
        module.save_model(Path(out, "model"), state_dict=state)


if __name__ == "__main__":
    _rank_main(sys.argv[1], sys.argv[2], int(sys.argv[3]), len(sys.argv) > 4 and sys.argv[4] == "lora")
