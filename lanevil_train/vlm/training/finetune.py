"""Fine-tuning any Hugging Face VLM through Lightning: LoRA (peft) or full, the answer tokens' NLL, resumable.

VLMFineTuner loads a saved image-text-to-text model and trains it on ClipQADataset batches with the very encode /
loss code HFVLM evaluates with (HFVLM.wrap around the model being trained): the loss is the mean NLL of each
answer's tokens (and, with train_eos, of the end-of-turn token after it), the prompt, frames and question being
labelled IGNORE_INDEX. With `lora` only adapter weights train, on the language model's attention and MLP
projections by default (never the vision tower); without it every weight trains except the vision tower when
`freeze_vision`. Lightning checkpoints hold only the trainable weights plus the hyperparameters (the base model's
directory and the LoRA settings), so a LoRA checkpoint stays small and `trainer.fit(ckpt_path=...)` resumes.
`save_model` writes the peft adapter, or the merged / fully trained model, beside the processor.
"""

from __future__ import annotations

import copy
import math
import os
import re
import shutil
import tempfile
from pathlib import Path

import pytorch_lightning as pl
import torch

from lanevil_train.rules import any_of, boolean, check_settings, integer, null_or, number, string_list, text
from lanevil_train.vlm.backends.hf import (
    ADAPTER_CONFIG,
    DTYPES,
    FRAMES_AS,
    HFVLM,
    _check_architecture,
    _check_model_dir,
    _choice,
    _load_processor,
)
from lanevil_train.vlm.clips.qa_data import ClipQADataset, clip_images, collate_clip_qa
from lanevil_train.vlm.training.vision_maps import VISION_LAYERS, VisionMaps, vision_layer

ADAPTER_NAME = "default"  # peft's name for the one adapter get_peft_model adds

__all__ = ["ClipQADataset", "collate_clip_qa", "clip_images", "VLMFineTuner", "default_lora_targets",
           "vision_tower_names"]

# Attribute names of the vision tower and of the language model across the image-text-to-text families.
VISION_TOWERS = ("vision_tower", "visual", "vision_model")
LANGUAGE_MODELS = ("language_model", "text_model")
LORA_PROJECTIONS = ("q_proj", "k_proj", "v_proj", "o_proj", "gate_proj", "up_proj", "down_proj")
LORA_KEYS = ("r", "alpha", "dropout", "target_modules")
# What a good value of each LoRA setting (model.lora.*) and each fine-tuning setting of the constructor
# (model.fine_tune.*) is: checked here, and by the config check under those keys before any work.
LORA_SETTINGS = {"r": integer(1), "alpha": number(0, low_open=True), "dropout": number(0, 1, high_open=True),
                 "target_modules": null_or(any_of(text(), string_list()))}
FINE_TUNE_SETTINGS = {"lr": number(0, low_open=True), "weight_decay": number(0), "warmup_steps": integer(0),
                      "freeze_vision": boolean(), "gradient_checkpointing": boolean(), "train_eos": boolean()}


def resolve_dtype(dtype: str) -> torch.dtype:
    """The training dtype: "auto" is bf16 on a CUDA device that supports it, else float32."""
    _choice("dtype", dtype, DTYPES)
    if dtype == "auto":
        cuda_bf16 = torch.cuda.is_available() and torch.cuda.is_bf16_supported()
        return torch.bfloat16 if cuda_bf16 else torch.float32
    return getattr(torch, dtype)


def vision_tower_names(model: torch.nn.Module) -> list[str]:
    """Qualified names of the model's vision tower modules (outermost ones only), found by the families' names."""
    found: list[str] = []
    for name, _ in model.named_modules():
        if name.rsplit(".", 1)[-1] in VISION_TOWERS and not any(name.startswith(f + ".") for f in found):
            found.append(name)
    return found


def default_lora_targets(model: torch.nn.Module, names: list[str] | None = None) -> str:
    """A peft target_modules regex: the Linear layers named `names` (default: attention and MLP projections)
    inside the language model, never the vision tower; a ValueError when it matches none."""
    names = list(LORA_PROJECTIONS if names is None else names)
    if not names or not all(isinstance(n, str) and n for n in names):
        raise ValueError(f"lora.target_modules: expected null or a non-empty list of module names, got {names!r}")
    pattern = rf"(?:.*\.)?(?:{'|'.join(LANGUAGE_MODELS)})\..*\.(?:{'|'.join(map(re.escape, names))})"
    linear = [n for n, m in model.named_modules() if isinstance(m, torch.nn.Linear) and re.fullmatch(pattern, n)]
    if not linear:
        raise ValueError(f"lora.target_modules: no Linear layer named {', '.join(names)} in the language model "
                         f"({type(model).__name__}); expected names such as {', '.join(LORA_PROJECTIONS)}")
    return pattern


def check_lora(lora) -> dict | None:
    """The LoRA settings with defaults filled in (r 16, alpha 32, dropout 0.05, per-family targets), else an error."""
    if lora is None:
        return None
    if not isinstance(lora, dict) and hasattr(lora, "items"):
        lora = dict(lora.items())
    if not isinstance(lora, dict):
        raise ValueError(f"lora: expected null or a mapping with {', '.join(LORA_KEYS)}, got {type(lora).__name__}")
    unknown = sorted(set(lora) - set(LORA_KEYS))
    if unknown:
        raise ValueError(f"lora: unknown keys {', '.join(unknown)}; expected some of {', '.join(LORA_KEYS)}")
    settings = {"r": 16, "alpha": 32, "dropout": 0.05, "target_modules": None, **lora}
    check_settings(LORA_SETTINGS, settings, "lora")
    targets = settings["target_modules"]
    if targets is not None:
        settings["target_modules"] = [targets] if isinstance(targets, str) else list(targets)
    return settings


class VLMFineTuner(pl.LightningModule):
    """A Hugging Face VLM trained on (clip, question, answer) batches: LoRA or full fine-tuning, answer-only loss.

    In the training step a batch holds its frames as float `images` (B*6, 3, H, W) in [0, 1] (and each frame's
    `lanes` when the suite knows them), the tensor visual defenses edit (BatchAdapter(images="images",
    lanes="lanes")) and the loss reads, through the processor's own torch operations, so gradients reach the
    pixels (PGD). training_step returns each frame's clip loss as `per_sample_loss` for AAM's hard examples;
    `attention_layer` names the vision layer AAM takes its map from and `vision_maps` lays its tokens on the frames;
    `attention_gradients` (switched on by AAM) lets the frames take gradients so a frozen tower's layer gets them.
    """

    attention_gradients = False

    def __init__(self, model_dir: str, lora: dict | None = None, freeze_vision: bool = True,
                 gradient_checkpointing: bool = False, lr: float = 1e-4, weight_decay: float = 0.0,
                 warmup_steps: int = 0, frames_as: str = "auto", dtype: str = "float32", train_eos: bool = True):
        """Load the model at `model_dir`, wrap it with LoRA adapters when `lora` is given, freeze what stays fixed."""
        super().__init__()
        model_dir = str(_check_model_dir(model_dir))
        lora = check_lora(lora)
        check_settings(FINE_TUNE_SETTINGS, locals(), "fine_tune")
        _choice("frames_as", frames_as, FRAMES_AS)
        self.save_hyperparameters({"model_dir": model_dir, "lora": lora, "freeze_vision": bool(freeze_vision),
                                   "gradient_checkpointing": bool(gradient_checkpointing), "lr": float(lr),
                                   "weight_decay": float(weight_decay), "warmup_steps": warmup_steps,
                                   "frames_as": frames_as, "dtype": dtype, "train_eos": bool(train_eos)})
        self.model_type = _check_architecture(Path(model_dir))
        self.processor = _load_processor(Path(model_dir))
        self.model = self._build_model(model_dir, lora, resolve_dtype(dtype))
        self.strict_loading = False  # checkpoints hold only the trainable weights; on_load_checkpoint checks them
        self.vision_maps = VisionMaps(self.processor, self.model_type, self._wrapped().frames_as)

    def _build_model(self, model_dir: str, lora: dict | None, dtype: torch.dtype) -> torch.nn.Module:
        """The base model in `dtype`, vision tower frozen, LoRA-wrapped when asked, checkpointing on when asked."""
        from transformers import AutoModelForImageTextToText

        model = AutoModelForImageTextToText.from_pretrained(model_dir, local_files_only=True, dtype=dtype)
        if self.hparams.freeze_vision:
            for name in vision_tower_names(model):
                model.get_submodule(name).requires_grad_(False)
        if self.hparams.gradient_checkpointing:
            model.gradient_checkpointing_enable(gradient_checkpointing_kwargs={"use_reentrant": False})
            model.config.use_cache = False
        if lora is not None:
            from peft import LoraConfig, get_peft_model

            config = LoraConfig(r=lora["r"], lora_alpha=lora["alpha"], lora_dropout=lora["dropout"],
                                target_modules=default_lora_targets(model, lora["target_modules"]), bias="none")
            model = get_peft_model(model, config)
        return model.train()

    # ---- the model behind the VLM interface ----------------------------------------------------------------------

    def vlm(self, **generation) -> HFVLM:
        """The model being trained behind the VLM interface (eval mode), for evaluation with HFVLM's settings
        (max_new_tokens, batch_size, system_prompt, ...)."""
        self.model.eval()
        generation.setdefault("frames_as", self.hparams.frames_as)
        return HFVLM.wrap(self.model, self.processor, self.hparams.model_dir, **generation)

    def _wrapped(self) -> HFVLM:
        return HFVLM.wrap(self.model, self.processor, self.hparams.model_dir, frames_as=self.hparams.frames_as)

    def batch_loss(self, batch: dict) -> torch.Tensor:
        """Per-sample mean NLL [B] of the answers (and end-of-turn tokens with train_eos) of a batch: its float
        `images` (on_after_batch_transfer's), or the uint8 `frames` of a batch straight from collate_clip_qa."""
        hf = self._wrapped()
        for key in ("questions", "answers"):
            if not isinstance(batch.get(key), list):
                raise ValueError(f"batch[{key!r}]: expected a list of strings (collate_clip_qa's batch), got "
                                 f"{type(batch.get(key)).__name__}")
        images = batch["images"] if "images" in batch else clip_images(batch["frames"])
        if self.attention_gradients and not images.requires_grad:  # a frozen tower's layer gets its gradient
            images = images.detach().requires_grad_(True)
        clips = images.unflatten(0, (len(batch["questions"]), -1))
        encoded = hf.encode(clips, batch["questions"], batch["answers"], label_eos=self.hparams.train_eos)
        self.vision_maps.observe(encoded.inputs, clips.shape[0], clips.shape[1], tuple(clips.shape[-2:]))
        return hf.loss_from_embeds(encoded, hf.embed(encoded))

    def attention_layer(self, layer: str = "auto") -> str:
        """The name in this module of the model's layer `layer` (auto: the family's vision output,
        vision_maps.VISION_LAYERS), whatever wrappers (peft) put before it: AAM's `layer`."""
        name = vision_layer(self.model_type, layer)
        found = [full for full, _ in self.named_modules() if full == f"model.{name}" or full.endswith(f".{name}")]
        if len(found) != 1:
            raise ValueError(f"model.attention_layer: {name!r} names {len(found)} modules of the {self.model_type} "
                             f"model ({found[:3]}); expected one, a dotted name as in the Hugging Face model (e.g. "
                             f"{vision_layer(self.model_type) if self.model_type in VISION_LAYERS else 'model.visual'}"
                             ")")
        return found[0]

    # ---- Lightning hooks -----------------------------------------------------------------------------------------

    def on_train_start(self) -> None:
        """Training mode for the whole model (from_pretrained leaves it in eval mode), dropout on; also when a fit
        resumes inside an epoch, where Lightning calls no on_train_epoch_start."""
        self.model.train()

    def on_train_epoch_start(self) -> None:
        """Training mode again after an epoch's validation or a vlm() view (both leave the model in eval mode)."""
        self.model.train()

    def on_after_batch_transfer(self, batch, dataloader_idx: int):
        """The batch's uint8 frames become the float images the step (and any visual defense) works on."""
        if isinstance(batch, dict) and "frames" in batch:
            batch["images"] = clip_images(batch.pop("frames"))
        return batch

    def training_step(self, batch: dict, batch_idx: int) -> dict:
        per_sample = self.batch_loss(batch)
        loss = per_sample.mean()
        self.log("train/loss", loss, prog_bar=True, batch_size=len(batch["questions"]))
        frames = len(batch["images"]) if "images" in batch else batch["frames"].shape[:2].numel()
        return {"loss": loss, "per_sample_loss": per_sample.detach().repeat_interleave(frames // len(per_sample))}

    def validation_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        loss = self.batch_loss(batch).mean()
        self.log("val/loss", loss, prog_bar=True, batch_size=len(batch["questions"]))
        return loss

    def configure_optimizers(self):
        """AdamW on the trainable parameters; linear warmup over warmup_steps, then cosine decay to 0."""
        params = [p for p in self.model.parameters() if p.requires_grad]
        if not params:
            raise ValueError(f"{self.hparams.model_dir}: no trainable parameter (everything is frozen)")
        optimizer = torch.optim.AdamW(params, lr=self.hparams.lr, weight_decay=self.hparams.weight_decay)
        total = _total_steps(self.trainer)
        warmup = self.hparams.warmup_steps
        scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: _warmup_cosine(step, warmup, total))
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}

    def trainable_keys(self) -> set[str]:
        """State-dict names of the weights that train (the only ones a checkpoint keeps); under trainer=fsdp the
        wrappers' name parts are left out, as in the state dict FSDP gathers."""
        return {name.replace("_fsdp_wrapped_module.", "").replace("_checkpoint_wrapped_module.", "")
                for name, param in self.named_parameters() if param.requires_grad}

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        """Keep only the trainable weights: the rest is the base model at hparams.model_dir."""
        keep = self.trainable_keys()
        checkpoint["state_dict"] = {k: v for k, v in checkpoint["state_dict"].items() if k in keep}

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        """Refuse a checkpoint whose weights are not exactly this module's trainable ones (under trainer=fsdp the
        strategy has loaded and removed them before this hook: nothing left to check)."""
        if "state_dict" not in checkpoint:
            return
        saved, wanted = set(checkpoint["state_dict"]), self.trainable_keys()
        if saved != wanted:
            missing, extra = sorted(wanted - saved), sorted(saved - wanted)
            raise ValueError(f"checkpoint: its weights do not match this fine-tuning setup (model_dir "
                             f"{self.hparams.model_dir}, lora {self.hparams.lora}): {len(missing)} trainable weights "
                             f"missing (e.g. {missing[:2]}), {len(extra)} unexpected (e.g. {extra[:2]})")

    # ---- saving for evaluation -----------------------------------------------------------------------------------

    def save_model(self, out_dir: str | os.PathLike, merge: bool = False, state_dict: dict | None = None) -> Path:
        """Save the processor and the peft adapter (LoRA; merge=False), or the merged / fully trained model, to
        `out_dir` (replaced whole, atomically): loadable by HFVLM(model_dir, adapter=out_dir) or HFVLM(out_dir).
        `state_dict`: this module's whole state dict gathered from a sharded run (sharding.gathered_state_dict),
        saved instead of the module's own weights, which hold only this rank's shard there."""
        if state_dict is not None and merge and self.hparams.lora is not None:
            raise ValueError("merge: a LoRA adapter gathered from a sharded run cannot be merged here; save it "
                             "unmerged and merge when loading (HFVLM(model_dir, adapter=..., merge_adapter=True))")
        gathered_adapter = state_dict is not None and self.hparams.lora is not None
        weights = {} if state_dict is None or gathered_adapter else {"state_dict": {
            key[len("model."):]: value for key, value in state_dict.items() if key.startswith("model.")}}
        out = Path(out_dir)
        _check_replaceable(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".partial", dir=out.parent))
        try:
            if gathered_adapter:
                self._save_gathered_adapter(staging, state_dict)
            else:
                self._model_to_save(merge).save_pretrained(staging, **weights)
            self.processor.save_pretrained(staging)
            _replace_dir(staging, out)
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
        return out

    def _save_gathered_adapter(self, out: Path, state_dict: dict) -> None:
        """peft's adapter files (adapter_config.json, adapter_model.safetensors) from a gathered state dict: its
        trainable (adapter) weights under peft's saved names, i.e. without the adapter's name. peft's own
        save_pretrained picks the adapter weights by walking the model's modules, whose names FSDP has changed."""
        from safetensors.torch import save_file

        adapter = f".{ADAPTER_NAME}."
        tensors = {key[len("model."):].replace(adapter, "."): state_dict[key].contiguous()
                   for key in sorted(self.trainable_keys())}
        if not tensors or any(adapter not in key for key in self.trainable_keys()):
            raise ValueError(f"state_dict: expected only LoRA weights of adapter {ADAPTER_NAME!r} to train, got "
                             f"{sorted(self.trainable_keys())[:3]}")
        save_file(tensors, str(out / "adapter_model.safetensors"), metadata={"format": "pt"})
        self.model.peft_config[ADAPTER_NAME].save_pretrained(str(out))

    def _model_to_save(self, merge: bool) -> torch.nn.Module:
        """The adapter-carrying model, a merged copy of it (the training model is left as it is), or the full one."""
        if self.hparams.lora is None or not merge:
            return self.model
        return copy.deepcopy(self.model).merge_and_unload()


class SkipTrainedBatches(pl.Callback):
    """Resuming from a checkpoint taken inside an epoch, Lightning restarts the epoch's data from its start (the
    loader keeps no position) while counting on from the saved batch, so the resumed run would train on the
    epoch's first batches again and never see its last ones. This tells the sampler (WindowShuffleSampler, whose
    order is fixed by seed and epoch) to leave out the batches the checkpoint has already trained on: a resumed run
    then sees exactly the batches an uninterrupted one would."""

    def __init__(self, sampler, batch_size: int):
        self.sampler, self.batch_size = sampler, batch_size

    def on_train_start(self, trainer, pl_module) -> None:
        """Before the first batch of a fit (Lightning calls no on_train_epoch_start for a resumed epoch)."""
        per_epoch = trainer.num_training_batches
        if not isinstance(per_epoch, int) or per_epoch <= 0:
            return
        done = trainer.global_step * trainer.accumulate_grad_batches - trainer.current_epoch * per_epoch
        if 0 < done < per_epoch:
            self.sampler.skip(done * self.batch_size * trainer.world_size)


def _total_steps(trainer) -> int:
    """The run's optimizer steps (max_steps, else Lightning's estimate), at least 1."""
    if trainer is None:
        return 1
    if trainer.max_steps and trainer.max_steps > 0:
        return trainer.max_steps
    estimate = trainer.estimated_stepping_batches
    return max(1, int(estimate)) if math.isfinite(estimate) else 1


def _warmup_cosine(step: int, warmup: int, total: int) -> float:
    """The learning-rate factor at `step`: linear from 0 to 1 over `warmup` steps, then cosine to 0 at `total`."""
    if step < warmup:
        return (step + 1) / (warmup + 1)
    progress = min(1.0, (step - warmup) / max(1, total - warmup))
    return 0.5 * (1.0 + math.cos(math.pi * progress))


def _check_replaceable(out: Path) -> None:
    """Refuse to replace a directory that is not a saved model or adapter (it could hold anything)."""
    if out.exists() and any(out.iterdir()):
        if not ((out / "config.json").is_file() or (out / ADAPTER_CONFIG).is_file()):
            raise FileExistsError(f"out_dir {out}: exists and holds no saved model or adapter; expected a new, "
                                  f"empty or previously saved directory")


def _replace_dir(staging: Path, out: Path) -> None:
    """Rename `staging` to `out`; an old `out` is moved aside first and removed after, so `out` is never half."""
    old = None
    if out.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old.", suffix=".partial", dir=out.parent))
        os.replace(out, old / out.name)
    os.replace(staging, out)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def load_finetuned(path: str | os.PathLike, option: str = "ckpt_path") -> VLMFineTuner:
    """The fine-tuned model a task=train checkpoint holds: its base model (hparams.model_dir, which must still be on
    disk) with the checkpoint's trainable weights; errors name `option` and the file."""
    from lanevil_train.checkpoints import check_vlm_checkpoint, read_lightning_checkpoint

    checkpoint = read_lightning_checkpoint(path, option)
    check_vlm_checkpoint(checkpoint, f"{option}={path}")
    hparams = checkpoint["hyper_parameters"]
    if not Path(hparams["model_dir"]).is_dir():
        raise FileNotFoundError(f"{option}={path}: the checkpoint's base model {hparams['model_dir']} is gone; "
                                f"evaluate the run's saved model/ folder with model.path (or model.adapter) instead")
    module = VLMFineTuner(**hparams)
    module.on_load_checkpoint(checkpoint)
    module.load_state_dict(checkpoint["state_dict"], strict=False)
    return module
