"""task=train for a VLM (model=vlm/embedded or model=vlm/hf): fine-tune on the clip suite's training split through
the Lightning trainer (checkpoints, resume with ckpt_path, logging, progress), save the model in the Hugging Face
format, then (task.test_after_fit) evaluate it on the test clips like task=evaluate.

    python -m lanevil_train task=train model=vlm/embedded              # the small VLM built here
    python -m lanevil_train task=train model=vlm/hf model.path=DIR     # LoRA (model.lora) or full
"""

from __future__ import annotations

from pathlib import Path

import pytorch_lightning as pl
from omegaconf import DictConfig, OmegaConf

from lanevil_train.checkpoints import (
    EMBEDDED_BASE_FOLDER,
    check_vlm_checkpoint,
    read_lightning_checkpoint,
    remove_stale_checkpoint_temporaries,
)
from lanevil_train.tasks.builders import build_callbacks, build_split, build_trainer, instantiate_at, output_dir
from lanevil_train.tasks.vlm.builders import (
    MODEL_FOLDER,
    check_vlm_run,
    fine_tunes,
    generation_settings,
    is_prompt_defense,
    spread,
    trained_model,
    with_model,
)
from lanevil_train.tasks.vlm.defense import tune_prompt_defense
from lanevil_train.tasks.vlm.evaluate import test_vlm

TOKENIZER_CLIPS = 600  # base clips of the train split whose QA texts train the embedded VLM's tokenizer
def lora_settings(cfg: DictConfig) -> dict | None:
    """model.lora as a plain dict, or None for full fine-tuning."""
    lora = cfg.model.get("lora")
    return None if lora is None else OmegaConf.to_container(lora, resolve=True)


def base_model_dir(cfg: DictConfig, train_set, out: Path) -> Path:
    """The model the run starts from: model=vlm/hf's model.path, or, for model=vlm/embedded, the small VLM built
    into out/init from the training split's QA texts (a resumed run reuses the one its checkpoint names)."""
    saved = None
    if cfg.ckpt_path is not None:  # resuming: a VLM's checkpoint (a lane detector's is named as one)
        saved = check_vlm_checkpoint(read_lightning_checkpoint(cfg.ckpt_path, "ckpt_path"),
                                     f"ckpt_path={cfg.ckpt_path}")
    if cfg.model.get("embedded") is None:
        return Path(cfg.model.path)
    if saved and Path(saved).is_dir():
        return Path(saved)
    from lanevil_train.vlm.backends.embedded import make_embedded_vlm, pretrain_vision, qa_corpus, save_model_dir

    init = out / EMBEDDED_BASE_FOLDER
    if not (init / "config.json").is_file():
        settings = OmegaConf.to_container(cfg.model.embedded, resolve=True)
        pretraining = settings.get("vision_pretraining") or {"steps": 0}
        all_bases = list(dict.fromkeys(train_set.clip_meta(i)["base_clip_id"] for i in range(len(train_set))))
        bases = spread(all_bases, TOKENIZER_CLIPS)  # the templates' words: a spread sample is enough
        scenes = spread(all_bases, pretraining["clips"]) if pretraining["steps"] else []
        rendered = prepare_clips(train_set, bases, scenes, render_workers(settings.get("workers", "auto")),
                                 cfg.progress)
        qas = [qa for base in bases for qa in train_set.qa_for(base)]
        if cfg.model.fine_tune.get("aids"):  # the training aids it will train on, too
            qas += [aid for base in bases for aid in train_set.training_aids_for(base)]
        model, processor = make_embedded_vlm(qa_corpus(qas), frame_size=tuple(settings["frame_size"]),
                                             seed=settings["seed"], **settings["sizes"])
        if pretraining["steps"]:
            sample = scene_batches(train_set, rendered, pretraining["batch"], seed=settings["seed"])
            pretrain_vision(model, processor, sample, pretraining["steps"], lr=pretraining["lr"],
                            mirror=pretraining.get("mirror", True), seed=settings["seed"], progress=cfg.progress)
        save_model_dir(model, processor, init)
    return init


def render_workers(workers: int | str) -> int:
    """model.embedded.workers (checked with the config) as a process count: auto is one per CPU core this process
    may use, at most 8 (each worker starts a Python with torch, and the work is about a thousand clips)."""
    import os

    if workers != "auto":
        return int(workers)
    return min(8, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)


def prepare_clips(train_set, bases: list[str], scenes: list[str], workers: int, progress: str = "auto") -> dict:
    """The truth of the train split's base clips `bases` (the tokenizer's corpus) and `scenes` (the vision
    pretraining's), and the frames of every variant of `scenes`, computed in `workers` processes:
    {scene base clip id: its variants' frames} (SyntheticClipSuite.prepare). A split on disk has no truth: its QA is
    read as it is, and vision pretraining is refused naming the setting."""
    if not hasattr(train_set, "prepare"):
        if scenes:
            raise ValueError(f"model.embedded.vision_pretraining: the vision tower learns from the scene truth, which "
                             f"{type(train_set).__name__} does not keep; train on a synthetic split (data=clips) or "
                             f"set model.embedded.vision_pretraining.steps=0")
        return {}
    return train_set.prepare(list(dict.fromkeys([*bases, *scenes])), render=scenes, workers=workers,
                             progress=progress)


def scene_batches(suite, rendered: dict, batch: int, seed: int):
    """`sample_batch(step) -> (clips, scene classes)` for embedded.pretrain_vision: every variant of the base clips
    `rendered` holds (prepare_clips'), with its base clip's scene classes, kept in memory and drawn at random."""
    import numpy as np

    clips, classes = [], []
    for base, variants in rendered.items():
        for frames in variants:
            clips.append(np.stack([np.asarray(frame, dtype=np.uint8) for frame in frames]))
            classes.append(suite.scene_classes_for(base))
    rng = np.random.default_rng(seed)

    def sample_batch(step: int):
        chosen = rng.integers(len(clips), size=batch)
        return [clips[i] for i in chosen], [classes[i] for i in chosen]

    return sample_batch


def train_vlm(cfg: DictConfig) -> float | None:
    """Fine-tune the VLM (with the visual part of the defense: PGD, MixUp, AAM, AAM++ on its frames), then, for a
    defense with a textual part, tune that for the fine-tuned model (defense=mida: AAM++ then PAT++); a textual
    defense alone (pat++, pat, self_reminder) is tuned for the trained model given, which stays as it is. Returns
    the headline score on the perturbed test clips when the test runs, else None."""
    from lanevil_train.vlm.clips.qa_data import ClipQADataset, MixingClipCollate, collate_clip_qa
    from lanevil_train.vlm.training.finetune import SkipTrainedBatches, VLMFineTuner

    pl.seed_everything(cfg.seed, workers=True)
    if is_prompt_defense(cfg) and not fine_tunes(cfg.defense):  # a prompt for the frozen model: no weight changes
        return tune_prompt_defense(cfg)
    check_vlm_run(cfg)
    check_sharded_merge(cfg)
    out = output_dir(cfg)
    train_set, val_set = build_split(cfg, "train"), (build_split(cfg, "val") if cfg.data.get("val") else None)
    check_lanes_for_defense(cfg, train_set)
    fine_tune = OmegaConf.to_container(cfg.model.fine_tune, resolve=True)
    variants, aids = fine_tune.pop("variants", "all"), fine_tune.pop("aids", 0)
    module = VLMFineTuner(str(base_model_dir(cfg, train_set, out)), lora=lora_settings(cfg),
                          frames_as=cfg.model.get("frames_as", "auto"), dtype=cfg.model.get("dtype", "float32"),
                          **fine_tune)
    callback, mixer = visual_defense(cfg, module)
    loaders = _loaders(cfg, ClipQADataset(train_set, variants=variants, aids=aids),
                       ClipQADataset(val_set, variants="clean") if val_set is not None else None,
                       MixingClipCollate(mixer) if mixer is not None else collate_clip_qa, collate_clip_qa)
    callbacks = build_callbacks(cfg)
    remove_stale_checkpoint_temporaries(callbacks)
    callbacks.append(SkipTrainedBatches(loaders[0].sampler, cfg.data.batch_size))
    if callback is not None:
        callbacks.append(callback)
    trainer = build_trainer(cfg, callbacks=callbacks)
    trainer.fit(module, *loaders, ckpt_path=cfg.ckpt_path)
    saved = _save(cfg, trainer, module, out / MODEL_FOLDER)
    if not trainer.is_global_zero:
        return None
    model = trained_model(cfg, saved)
    print(f"trained model: {saved} (evaluate it with task=evaluate model=vlm/hf "
          f"{' '.join(f'model.{k}={v}' for k, v in model.items() if v is not None)})")
    if is_prompt_defense(cfg):  # defense=mida: the textual part tuned for the model just trained
        return tune_prompt_defense(with_model(cfg, model))
    if not cfg.task.test_after_fit:
        return None
    return _test(cfg, saved, out / "test")


def visual_defense(cfg: DictConfig, module) -> tuple:
    """(callback, mixer) of the defense for a VLM being fine-tuned: AAM / AAM++ on the vision layer
    model.attention_layer names (its tokens laid on the frames by module.vision_maps) with each frame's lanes, PGD
    on the float frames in [0, 1] pixel units; a user's own callback as configured."""
    from hydra.utils import get_class

    from lanevil_train.callbacks import AttentionAreaMixing, BatchAdapter, PGDAdversarialTraining
    defense = cfg.defense
    mixer = instantiate_at(defense.mixer, "defense.mixer") if defense.get("mixer") is not None else None
    node = defense.get("callback")
    if node is None:
        return None, mixer
    target = get_class(node._target_)
    extra = {}
    if issubclass(target, AttentionAreaMixing):
        try:
            layer = module.attention_layer(cfg.model.get("attention_layer", "auto"))
        except ValueError as error:
            raise ValueError(f"defense={defense.name}: {error}") from None
        extra = {"layer": layer, "feature_map": module.vision_maps,
                 "adapter": BatchAdapter(images="images", lanes="lanes")}
    elif issubclass(target, PGDAdversarialTraining):  # the frames are [0, 1] pixels, not normalised
        extra = {"mean": (0.0, 0.0, 0.0), "std": (1.0, 1.0, 1.0), "adapter": BatchAdapter(images="images")}
    return instantiate_at(node, "defense.callback", **extra), mixer


def check_lanes_for_defense(cfg: DictConfig, train_set) -> None:
    """AAM compares a frame's attention with its lanes: the train split must know them (a synthetic split does)."""
    from hydra.utils import get_class

    from lanevil_train.callbacks import AttentionAreaMixing

    node = cfg.defense.get("callback")
    if node is not None and issubclass(get_class(node._target_), AttentionAreaMixing) and \
            not hasattr(train_set, "lanes_for"):
        raise ValueError(f"defense={cfg.defense.name}: AAM compares each frame's attention with its lanes, which "
                         f"{type(train_set).__name__} does not keep; train on a synthetic split (data=clips)")


def _save(cfg: DictConfig, trainer: pl.Trainer, module, folder: Path) -> Path:
    """The trained model (or LoRA adapter) saved in the Hugging Face format by rank 0; under trainer=fsdp every rank
    first takes part in gathering the whole state dict onto rank 0 (sharding.gathered_state_dict)."""
    from lanevil_train.vlm.training.sharding import gathered_state_dict

    state = gathered_state_dict(trainer)
    if trainer.is_global_zero:
        module.save_model(folder, merge=bool(cfg.model.get("merge_adapter", False)), state_dict=state)
    return folder


def check_sharded_merge(cfg: DictConfig) -> None:
    """Merging LoRA into the base weights needs the whole model in one process, which trainer=fsdp exists to avoid:
    refuse model.merge_adapter there before any step (the adapter saves, and merges when loaded for evaluation)."""
    strategy = cfg.trainer.get("strategy")
    target = strategy.get("_target_", "") if OmegaConf.is_dict(strategy) else str(strategy or "")
    if cfg.model.get("lora") is not None and cfg.model.get("merge_adapter") and "FSDP" in target.upper():
        raise ValueError("model.merge_adapter: true cannot merge under trainer=fsdp (the model is sharded over the "
                         "ranks); train with model.merge_adapter=false and merge at evaluation: task=evaluate "
                         "model=vlm/hf model.path=BASE model.adapter=RUN/model model.merge_adapter=true")


def _loaders(cfg: DictConfig, train, val, collate, val_collate):
    """The training pairs shuffled a window of data.shuffle_window base clips at a time (each base clip rendered or
    read once per epoch), the validation pairs in order."""
    from torch.utils.data import DataLoader

    from lanevil_train.vlm.clips.qa_data import WindowShuffleSampler

    common = {"batch_size": cfg.data.batch_size, "num_workers": cfg.data.num_workers,
              "persistent_workers": cfg.data.num_workers > 0}
    sampler = WindowShuffleSampler(train, cfg.data.shuffle_window, seed=cfg.seed)
    return (DataLoader(train, sampler=sampler, collate_fn=collate, **common),
            DataLoader(val, shuffle=False, collate_fn=val_collate, **common) if val else None)


def _test(cfg: DictConfig, saved: Path, out: Path) -> float:
    """The saved model on the test clips, loaded as task=evaluate would (test_vlm)."""
    from lanevil_train.vlm.backends.hf import HFVLM

    settings = {**generation_settings(cfg), "dtype": cfg.model.get("dtype", "auto"),
                "device": cfg.model.get("device", "auto")}
    model = trained_model(cfg, saved)
    vlm = HFVLM(model["path"], adapter=model["adapter"], **settings)
    defense = "" if cfg.defense.name == "none" else f"+{cfg.defense.name}"
    return test_vlm(cfg, vlm, cfg.task.get("label") or f"{vlm.name}{defense}", out)


