"""The wiring the VLM tasks share (task=train, evaluate, compare and closed_loop with model=vlm/<backend>): the
backend and judge a config names, the clips to evaluate on, a trained run's model, the checks of a VLM training run,
and the textual defenses (defense=pat++, pat, self_reminder) as settings and as wrappers around a VLM. No task
function lives here, so the VLM task modules import it and never each other in a circle."""

from __future__ import annotations

import json
from pathlib import Path

from hydra.utils import get_class
from omegaconf import DictConfig, OmegaConf, open_dict

from lanevil_train.callbacks import AttentionAreaMixing
from lanevil_train.data.mixers import MixUp
from lanevil_train.errors import prefixed as prefixed_error
from lanevil_train.files.atomic import atomic_write_text
from lanevil_train.tasks.builders import build_split, instantiate_at
from lanevil_train.tasks.config_check import TRAINING_KEYS
from lanevil_train.vlm.backends.embedded import FAMILY
from lanevil_train.vlm.base import VLM
from lanevil_train.vlm.clips.clip_set import ClipSetDataset, SyntheticClipSuite
from lanevil_train.vlm.defenses.pat import PrefixedVLM, load_prefix
from lanevil_train.vlm.defenses.reminder import RemindedVLM
from lanevil_train.vlm.defenses.settings import PromptDefense
from lanevil_train.vlm.training.finetune import load_finetuned
from lanevil_train.vlm.training.vision_maps import vision_layer

MODEL_FOLDER = "model"  # the trained model (or adapter) in the Hugging Face format, in the run folder
# Generation and prompt settings of a local backend that a trained model (ckpt_path) is evaluated with.
GENERATION_KEYS = ("name", "max_new_tokens", "batch_size", "frames_as", "system_prompt", "do_sample", "temperature",
                   "seed")


def inference_node(model: DictConfig) -> DictConfig:
    """The model node without its training keys and its kind: what builds the inference backend."""
    return OmegaConf.masked_copy(model, [key for key in model if key not in (*TRAINING_KEYS, "kind")])


def generation_settings(cfg: DictConfig) -> dict:
    """The model node's generation and prompt settings (for a model trained here, loaded from its checkpoint)."""
    return {key: cfg.model[key] for key in GENERATION_KEYS if key in cfg.model}


def build_vlm(cfg: DictConfig) -> VLM:
    """The VLM backend cfg.model configures (a node with a `_target_`; its training keys left out), or, with
    ckpt_path, the model a task=train run saved in that checkpoint; built now: a bad path fails here."""
    if cfg.ckpt_path is not None:
        return load_finetuned(cfg.ckpt_path, "ckpt_path").vlm(**generation_settings(cfg))
    vlm = instantiate_at(inference_node(cfg.model), "model")
    if not isinstance(vlm, VLM):
        raise ValueError(f"model._target_={cfg.model._target_}: built a {type(vlm).__name__}, expected a "
                         f"lanevil_train.vlm.base.VLM")
    return vlm


def build_judge(cfg: DictConfig, out: Path):
    """The judge cfg.judge configures, or None (judge=none); an LLM judge's reply cache defaults to
    out/judge_cache.jsonl."""
    node = cfg.get("judge")
    if node is None or node.get("_target_") is None:
        return None
    extra = {"cache_path": str(out / "judge_cache.jsonl")} if "cache_path" in node and node.cache_path is None else {}
    return instantiate_at(node, "judge", **extra)


def clip_suite(cfg: DictConfig):
    """(dataset, name) of the clips to evaluate on: task.suite=synthetic (task.cases scenes rendered on the fly with
    task.illusions and task.severities; corruptions / combined: the corruption or illusion-pair suite of the
    clips), a folder written by task=build data=clips, a DriveLM-style QA JSON file, or (task.suite=null)
    data=clips' test split."""
    suite, task, clips = cfg.task.suite, cfg.task, cfg.data.name == "clips"
    if suite is None:
        if not clips:
            raise ValueError("task.suite: a VLM answers questions about clips: give task.suite=synthetic, a clip "
                             "suite folder (task=build data=clips) or a DriveLM QA JSON file, or use data=clips")
        return build_split(cfg, "test"), "clips-test"
    if suite in ("synthetic", "corruptions", "combined"):
        kind = {"synthetic": "illusions"}.get(suite, suite)
        first_seed = cfg.data.test.first_seed if clips else 1000000
        size = tuple(cfg.data.size) if clips else (360, 640)
        illusions = "all" if task.illusions == "all" else list(task.illusions)
        try:
            dataset = SyntheticClipSuite(task.cases, first_seed, illusions, tuple(task.severities), size, kind=kind)
        except ValueError as error:
            raise prefixed_error(error, f"task.suite={suite}") from None
        if kind != "illusions":
            return dataset, f"synthetic-clips-{kind}"
        return dataset, "synthetic-clips"
    path = Path(suite)
    try:
        if path.is_file() and path.suffix == ".json":
            return ClipSetDataset.from_drivelm(path), path.stem
        return ClipSetDataset(path), path.name
    except (FileNotFoundError, ValueError) as error:
        raise prefixed_error(error, f"task.suite={suite}") from None


def spread(items: list, count: int) -> list:
    """About `count` of `items`, evenly spread over them."""
    return items[::max(1, len(items) // count)]


def trained_model(cfg: DictConfig, saved: Path) -> dict:
    """model.path and model.adapter that load what a run saved in `saved`: its LoRA adapter on model.path, or the
    saved (merged, fully trained or embedded) model."""
    if cfg.model.get("embedded") is None and cfg.model.get("lora") is not None and \
            not cfg.model.get("merge_adapter", False):
        return {"path": str(cfg.model.path), "adapter": str(saved)}
    return {"path": str(saved), "adapter": None}


def with_model(cfg: DictConfig, model: dict) -> DictConfig:
    """A copy of cfg whose model node loads `model` (trained_model's path and adapter)."""
    cfg = cfg.copy()
    with open_dict(cfg):
        cfg.model.path, cfg.model.adapter = model["path"], model["adapter"]
    return cfg


def check_vlm_run(cfg: DictConfig) -> None:
    """A VLM training run's data and defense, before anything loads (task=compare checks every run so): a textual
    part's settings, and for a run that fine-tunes the clip suite's data and a visual part it can apply."""
    if is_prompt_defense(cfg):
        prompt_defense(cfg)
    if not fine_tunes(cfg.defense):
        return
    if cfg.data.name != "clips":
        raise ValueError(f"data: a VLM trains on the clip suite's QA: use data=clips (got data={cfg.data.name})")
    check_visual_defense(cfg)


def check_visual_defense(cfg: DictConfig) -> None:
    """VLM fine-tuning takes the defenses that act on a batch of frames: a Lightning callback (PGD, AAM, AAM++ or
    the user's own) and MixUp; image transforms and Copy-Paste work on lane-detector samples and are refused. AAM's
    attention layer `auto` must know the model's family (read from its config.json)."""
    defense = cfg.defense
    if defense.get("transforms"):
        raise ValueError(f"defense={defense.name}: its image transforms act on a lane detector's samples; VLM "
                         f"fine-tuning takes defenses on the batch's frames: pgd, mixup, aam, aam++ (and mida, or a "
                         f"textual defense: pat++, pat, self_reminder)")
    mixer = defense.get("mixer")
    if mixer is not None and not issubclass(get_class(mixer._target_), MixUp):
        raise ValueError(f"defense={defense.name}: {mixer._target_} moves lanes with their labels in a lane "
                         f"detector's batch; a clip's questions cannot follow it. VLM fine-tuning mixes clips with "
                         f"mixup only")
    callback = defense.get("callback")
    if callback is not None and issubclass(get_class(callback._target_), AttentionAreaMixing) and \
            cfg.model.get("attention_layer", "auto") == "auto":
        try:
            vision_layer(model_family(cfg))
        except ValueError as error:
            raise ValueError(f"defense={defense.name}: {error}") from None


def model_family(cfg: DictConfig) -> str:
    """The model_type of the VLM a run trains: the embedded VLM's, or that in model.path's config.json."""
    if cfg.model.get("embedded") is not None:
        return FAMILY
    config = Path(str(cfg.model.path)) / "config.json"
    try:
        return str(json.loads(config.read_text()).get("model_type"))
    except (OSError, ValueError) as error:
        raise ValueError(f"model.path: cannot read {config} ({error}); expected a saved Hugging Face model") from None


def is_prompt_defense(cfg: DictConfig) -> bool:
    """Whether cfg.defense is (or has) a textual defense of VLMs (it names a `prompt` method)."""
    return cfg.get("defense") is not None and cfg.defense.get("prompt") is not None


def fine_tunes(defense: DictConfig) -> bool:
    """Whether the defense changes the model's weights: a visual part (a callback or a mixer) that acts during
    fine-tuning (defense=none, aam++, mida ...), not only a prompt for the model as it is (pat++, pat, ...)."""
    return defense.get("prompt") is None or defense.get("callback") is not None or defense.get("mixer") is not None


def prompt_defense(cfg: DictConfig) -> PromptDefense:
    """cfg.defense of a textual defense, typed and checked once (vlm/defenses/settings.PromptDefense): a ValueError
    names every bad key."""
    return PromptDefense.from_settings(OmegaConf.to_container(cfg.defense, resolve=True), str(cfg.defense.name))


def check_prompt_model(cfg: DictConfig) -> None:
    """A prefix is tuned for a trained local model: model=vlm/hf or vlm/embedded, with model.path or ckpt_path."""
    target = cfg.model.get("_target_")
    if cfg.ckpt_path is None and target != "lanevil_train.vlm.backends.hf.HFVLM":
        raise ValueError(f"model: defense={cfg.defense.name} splices a prefix into a local model's token ids; use "
                         f"model=vlm/hf or model=vlm/embedded (got model._target_={target})")
    if cfg.ckpt_path is None and cfg.model.get("path") is None:
        raise ValueError(f"model.path: defense={cfg.defense.name} tunes a prefix for a trained model; give "
                         f"model.path=RUN/model (task=train model=vlm/embedded writes one) or ckpt_path=...")


def _prefix_path(defense: PromptDefense) -> str:
    """The tuned prefix a pat++ / pat defense applies (defense.prefix_path), or a ValueError saying how to get one."""
    if defense.prefix_path is None:
        raise ValueError(f"defense.prefix_path: defense={defense.name} applies a tuned prefix; give "
                         f"defense.prefix_path=RUN/prefix.json (task=train defense={defense.name} writes it)")
    return defense.prefix_path


def build_defended_vlm(cfg: DictConfig):
    """The VLM of model=vlm/<backend>, and when defense= is a textual one (self_reminder, or pat++ / pat with
    defense.prefix_path) the VLM answering through it; the defense's settings, its prefix file and a backend it can
    be spliced into are checked before the model loads (task=evaluate and task=closed_loop)."""
    if not is_prompt_defense(cfg):
        return build_vlm(cfg)
    defense = prompt_defense(cfg)
    if defense.tuned:
        _prefix_path(defense)
        check_prompt_model(cfg)
    return with_prompt_defense(build_vlm(cfg), defense)


def with_prompt_defense(vlm, defense: PromptDefense):
    """The VLM with its questions wrapped in the reminders (self_reminder), or with the tuned prefix of
    defense.prefix_path before every question (pat++, pat)."""
    name = f"{vlm.name}+{defense.name}"
    if not defense.tuned:
        return RemindedVLM(vlm, defense.before, defense.after, name=name)
    tokenizer = getattr(getattr(vlm, "processor", None), "tokenizer", None)
    return prefixed(vlm, load_prefix(_prefix_path(defense), tokenizer), name)


def prefixed(vlm, record: dict, name: str):
    """The VLM with a tuned prefix.json `record` before every question (its token ids, or its soft vectors)."""
    method = "PAT" if record.get("facts", {}).get("method") == "pat" else "PAT++"
    return PrefixedVLM(vlm, record["ids"], name=name, embeddings=record.get("embeddings"), method=method)


def describe_defense(vlm) -> str | None:
    """A markdown section naming the textual defense a VLM answers with (its prefix, or its reminders), else None."""
    if isinstance(vlm, PrefixedVLM) and vlm.embeddings is not None:
        return (f"## Defense: {vlm.method} soft prefix\n\nBefore every question, {len(vlm.prefix_ids)} tuned vectors "
                f"of width {vlm.embeddings.shape[1]} in place of the tokens {vlm.prefix_ids}\n")
    if isinstance(vlm, PrefixedVLM):
        text = vlm.vlm.processor.tokenizer.decode(vlm.prefix_ids)
        return (f"## Defense: {vlm.method} prefix\n\nBefore every question, {len(vlm.prefix_ids)} tokens: "
                f"`` {text} ``\n\nToken ids: {vlm.prefix_ids}\n")
    if isinstance(vlm, RemindedVLM):
        return (f"## Defense: Self-Reminder\n\nEvery question between\n\n> {vlm.before}\n\nand\n\n"
                f"> {vlm.after}\n")
    return None


def add_defense_to_report(out: Path, vlm) -> None:
    """Put the defense's section right after the title of out/report.md (when both exist)."""
    report, section = out / "report.md", describe_defense(vlm)
    if section is None or not report.is_file():
        return
    title, _, rest = report.read_text().partition("\n")
    atomic_write_text(report, f"{title}\n\n{section}{rest}")
