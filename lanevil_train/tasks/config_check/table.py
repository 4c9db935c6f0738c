"""RULES: every user-facing config key and its rule (a detector head's parameters are the head's own: head_rules in
__init__); reading a value from the composed config and applying a rule to it."""

from __future__ import annotations

from collections.abc import Collection
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue, OmegaConfBaseException

from lanevil_train.closed_loop.episode import LoopSettings
from lanevil_train.closed_loop.lane_keeper import KEEPER_SETTINGS
from lanevil_train.closed_loop.lateral_controllers import CONTROLLERS
from lanevil_train.closed_loop.longitudinal import AccSettings
from lanevil_train.closed_loop.policies import VLMPolicy
from lanevil_train.closed_loop.protocol import Protocol
from lanevil_train.closed_loop.tracker import TRACKERS
from lanevil_train.data.illusion_set import Plan
from lanevil_train.data.normalization import NORMALIZATIONS
from lanevil_train.data.resize import RESIZE_FILTERS
from lanevil_train.illusions import SEVERITIES
from lanevil_train.illusions.registry import ILLUSIONS
from lanevil_train.lanes import ROW_SAMPLINGS
from lanevil_train.models.backbones import OUTPUT_STRIDES
from lanevil_train.models.schedules import LR_SCALINGS
from lanevil_train.perturbations import SUITE_KINDS
from lanevil_train.predict.illusion import IllusionSettings
from lanevil_train.progress import MODES
from lanevil_train.report.leaderboard import SETTINGS as LEADERBOARD_SETTINGS
from lanevil_train.rules import (
    Rule,
    any_of,
    boolean,
    exactly,
    existing_dir,
    existing_file,
    int_list,
    int_pair,
    integer,
    is_list,
    null_or,
    number,
    ok,
    one_of,
    problem,
    string_list,
    text,
)
from lanevil_train.sim.vehicle import VehicleParams
from lanevil_train.tasks.config_check.config_rules import (
    _for_splits,
    api_key_variable,
    checkpoint_file,
    checkpoint_mapping,
    culane_rows,
    defense_keys,
    defense_names,
    http_url,
    illusion_names,
    illusion_suite,
    integer_in,
    mapping,
    odd_box,
    output_folder,
    rate_factors,
    seed_list,
    target_list,
    target_node,
    timm_model_name,
)
from lanevil_train.tasks.config_check.keys import SPLITS
from lanevil_train.tasks.search_settings import SearchSettings
from lanevil_train.vlm.clips.qa_data import PAIRING_SETTINGS
from lanevil_train.vlm.defenses.settings import SETTINGS as PROMPT_SETTINGS
from lanevil_train.vlm.training.finetune import FINE_TUNE_SETTINGS, LORA_SETTINGS

RULES: dict[str, Rule] = {
    # root
    "seed": integer(0, 2**32 - 1),
    "ckpt_path": null_or(checkpoint_file()),
    "progress": one_of(*MODES),
    # data
    "data.name": text(),
    "data.root": existing_dir("dataset directory"),
    "data.input_size": int_pair(16),
    "data.crop_top": number(0, 1, high_open=True),
    "data.normalize": one_of(*NORMALIZATIONS),
    "data.resize": one_of(*RESIZE_FILTERS),
    "data.batch_size": integer(1),
    "data.num_workers": integer(0),
    "data.augment": boolean(),
    "data.max_lanes": integer(1),
    "data.decode_topk": integer(1),  # data=curvelanes: the most lanes a capped decoding keeps (LaneATT's nms_topk)
    "data.train_transforms": null_or(target_list()),
    **{f"data.{split}": null_or(target_node()) for split in SPLITS},
    **_for_splits("num_scenes", integer(1)),
    **_for_splits("first_seed", integer(0)),
    **_for_splits("size", int_pair(16)),
    **_for_splits("cache", boolean()),
    # data=clips (the VLM clip suite)
    "data.size": int_pair(16),
    "data.per_clip": integer(1),
    "data.paraphrase": null_or(target_node()),
    "data.paraphrase.api_key_env": api_key_variable(),
    "data.illusions": illusion_names(),
    "data.severities": int_list(SEVERITIES[0], SEVERITIES[-1]),
    **_for_splits("num_cases", integer(1)),
    **_for_splits("per_clip", integer(1)),
    **_for_splits("cache_clips", integer(1)),
    "data.shuffle_window": integer(1),
    # model
    "model.name": text(),
    "model.attention_layer": text(),
    "model.head": target_node(),  # its parameters' rules: the head class's SETTINGS (head_rules, below)
    # the families' decoding options (checked against the head's decode keywords too: check_decode_options)
    "model.decode.local_maximum_window": any_of(one_of("auto"), integer(0)),
    "model.decode.max_lanes": null_or(integer(1)),
    "model.decode.kpt_threshold": number(0, 1),
    "model.decode.root_threshold": number(0),
    "model.decode.cluster_threshold": number(0, low_open=True),
    "model.decode.min_points": integer(1),
    "model.decode.extend_ends": boolean(),
    "model.decode.local_width": null_or(integer(0)),
    "model.decode.exist_threshold": number(0, 1),
    "model.decode.prob_threshold": number(0, 1),
    "model.decode.row_step": integer(1),
    "model.decode.lane_points": one_of("inside", "official"),
    "model.decode.official_writer": null_or(one_of("tusimple", "culane")),
    "model.decode.blur": odd_box(),
    "model.row_sampling": one_of(*ROW_SAMPLINGS),
    "model.culane_rows": culane_rows(),
    "model.neck": null_or(target_node()),
    "model.feature_strides": int_list(1),
    "model.output_stride": null_or(integer_in(OUTPUT_STRIDES)),
    "model.optimizer": target_node(),
    "model.optimizer.lr": number(0, low_open=True),
    "model.optimizer.weight_decay": number(0),
    "model.scheduler": null_or(target_node()),
    "model.reference_batch_size": null_or(integer(1)),
    "model.lr_scaling": one_of(*LR_SCALINGS),
    "model.lr_multipliers": null_or(rate_factors()),
    "model.gradient_clip_norm": null_or(number(0, low_open=True)),
    "model.decode.conf_threshold": number(0, 1),
    "model.decode.nms_threshold": number(0),
    "model.decode.nms_topk": null_or(integer(1)),
    # model=vlm/<backend> (VLMs)
    "model.path": null_or(existing_dir("directory of a saved Hugging Face model (save_pretrained)")),
    "model.adapter": null_or(existing_dir("directory of a peft adapter (a task=train run's model/ folder)")),
    "model.merge_adapter": boolean(),
    "model.lora": null_or(mapping()),  # its keys: SETTINGS_GROUPS (below)
    **{f"model.lora.{key}": rule for key, rule in LORA_SETTINGS.items()},  # the fine-tuner's own rules
    "model.fine_tune": mapping(),
    **{f"model.fine_tune.{key}": rule for key, rule in {**FINE_TUNE_SETTINGS, **PAIRING_SETTINGS}.items()},
    "model.embedded.workers": any_of(one_of("auto"), integer(0)),
    "model.embedded.vision_pretraining": null_or(mapping()),
    "model.embedded.vision_pretraining.steps": integer(0),
    "model.embedded.vision_pretraining.clips": integer(1),
    "model.embedded.vision_pretraining.batch": integer(1),
    "model.embedded.vision_pretraining.lr": number(0, low_open=True),
    "model.embedded.vision_pretraining.mirror": boolean(),
    "model.base_url": http_url(),
    "model.dtype": one_of("auto", "float32", "bfloat16", "float16"),
    "model.device": text(),
    "model.max_new_tokens": integer(1),
    "model.batch_size": integer(1),
    "model.frames_as": one_of("auto", "images", "video"),
    "model.system_prompt": null_or(text()),
    "model.api_key_env": api_key_variable(),
    "model.concurrency": integer(1),
    "model.max_retries": integer(0),
    "model.timeout_s": number(0, low_open=True),
    "model.temperature": number(0, 2),
    "model.image_format": one_of("png", "jpeg"),
    "model.jpeg_quality": integer(1, 100),
    "model.label": null_or(text()),
    # judge (VLM answers)
    "judge.base_url": http_url(),
    "judge.model": text(),
    "judge.api_key_env": api_key_variable(),
    "judge.cache_path": null_or(text()),
    "judge.concurrency": integer(1),
    "judge.max_retries": integer(0),
    "judge.model_dir": null_or(existing_dir("sentence-transformers model directory")),
    "judge.device": text(),
    "judge.batch_size": integer(1),
    # backbone
    "backbone": target_node(),
    "backbone.name": timm_model_name(),
    "backbone.pretrained": boolean(),
    "backbone.checkpoint": null_or(checkpoint_file("state dict file")),
    "backbone.out_indices": null_or(int_list()),
    "backbone.output_stride": null_or(integer_in(OUTPUT_STRIDES)),  # which stages each backbone has: check_feature_map
    # defense (its parameters: the constructors)
    "defense": defense_keys(),
    "defense.name": text(),
    "defense.transforms": null_or(target_list()),
    "defense.mixer": null_or(target_node()),
    "defense.callback": null_or(target_node()),
    # a textual defense's settings: its owner's rules (vlm/defenses/settings.py)
    **{f"defense.{key}": rule for key, rule in PROMPT_SETTINGS.items()},
    # task (each task has some of these)
    "task.name": text(),
    "task.out_dir": null_or(output_folder()),
    "task.cases": integer(0),
    "task.frames": integer(1),
    "task.illusions": illusion_names(),
    **{f"task.{key}": rule for key, rule in Plan.SETTINGS.items()},  # the suites' own rules
    "task.workers": integer(0),
    "task.fallback": boolean(),
    "task.test_after_fit": boolean(),
    "task.init_from": null_or(checkpoint_file()),
    "task.suite": illusion_suite(),
    "task.label": null_or(text()),
    "task.blind": any_of(boolean(), one_of("grey", "text", "all")),  # VLMs: true is grey (tasks/vlm/evaluate.py)
    "task.baseline": null_or(text()),
    "task.runs": string_list(),
    "task.defenses": defense_names(),
    "task.seeds": seed_list(),
    "task.run_only": null_or(text()),
    "task.bootstrap": integer(100),
    "task.confidence": number(0, 1, low_open=True, high_open=True),
    "task.kind": one_of(*SUITE_KINDS),
    "task.onnx": null_or(existing_file("ONNX model written by task=export")),
    "task.predictions": boolean(),
    "task.culane_categories": null_or(any_of(one_of("auto"), existing_dir("folder of the nine CULane category "
                                                                          "lists (list/test_split/)"))),
    "task.html": boolean(),  # report.html beside report.md (report/page/)
    "task.out": null_or(text()),
    "task.opset": integer(9),
    "task.tolerance": number(0, low_open=True),
    "task.decode.conf_threshold": null_or(number(0, 1)),
    "task.decode.nms_threshold": null_or(number(0)),
    "task.decode.nms_topk": null_or(integer(1)),
    # task=audit_qa
    "task.folds": integer(2),
    "task.min_count": integer(2),
    "task.alpha": number(0, 1, low_open=True, high_open=True),
    # task=closed_loop
    "task.policy": null_or(one_of("detector", "truth", "vlm")),
    "task.models": null_or(checkpoint_mapping()),
    **{f"task.{key}": rule for key, rule in Protocol.SETTINGS.items()},  # the closed-loop protocol's own rules
    **{f"task.{key}": rule for key, rule in LoopSettings.SETTINGS.items()},  # the loop's own rules
    "task.animate": boolean(),
    **{f"task.vehicle.{key}": rule for key, rule in VehicleParams.SETTINGS.items()},  # the vehicle's own rules
    **{f"task.acc.{key}": rule for key, rule in AccSettings.SETTINGS.items()},  # the ACC and emergency brake's
    "task.tracker": one_of(*TRACKERS),
    "task.controller": one_of(*CONTROLLERS),
    **{f"task.{key}": rule for key, rule in KEEPER_SETTINGS.items()},  # the lane keeper's own rules
    **{f"task.{name}.{key}": rule for name, owner in {**TRACKERS, **CONTROLLERS}.items()
       for key, rule in getattr(owner, "SETTINGS", {}).items()},
    **{f"task.vlm.{key}": rule for key, rule in VLMPolicy.SETTINGS.items()},  # the VLM policy's own rules
    # trainer (Lightning's Trainer arguments)
    "trainer.max_steps": any_of(exactly(-1), integer(1)),
    "trainer.max_epochs": null_or(any_of(exactly(-1), integer(1))),
    "trainer.min_steps": null_or(integer(0)),
    "trainer.min_epochs": null_or(integer(0)),
    "trainer.log_every_n_steps": integer(1),
    "trainer.check_val_every_n_epoch": null_or(integer(1)),
    "trainer.val_check_interval": null_or(any_of(integer(1), number(0, 1, low_open=True))),
    "trainer.limit_train_batches": null_or(any_of(integer(0), number(0, 1))),
    "trainer.limit_val_batches": null_or(any_of(integer(0), number(0, 1))),
    "trainer.limit_test_batches": null_or(any_of(integer(0), number(0, 1))),
    "trainer.num_sanity_val_steps": integer(-1),
    "trainer.gradient_clip_val": null_or(number(0)),
    "trainer.fast_dev_run": any_of(boolean(), integer(0)),
    "trainer.accumulate_grad_batches": integer(1),
}


# Settings groups one class owns whole: every key of such a mapping must be one of its settings (an unknown key is
# named by its dotted path with the nearest setting: cross.check_settings_groups); their values' rules are above.
SETTINGS_GROUPS: dict[str, Collection[str]] = {
    "task.vehicle": VehicleParams.SETTINGS,
    "task.acc": AccSettings.SETTINGS,
    "task.vlm": VLMPolicy.SETTINGS,
    **{f"task.{name}": owner.SETTINGS for name, owner in {**TRACKERS, **CONTROLLERS}.items()
       if getattr(owner, "SETTINGS", None)},
    "model.lora": LORA_SETTINGS,
    "model.fine_tune": {**FINE_TUNE_SETTINGS, **PAIRING_SETTINGS},
    "model.embedded.vision_pretraining": ("steps", "clips", "batch", "lr", "mirror"),
}

_ABSENT = object()


def _plain(value: Any) -> Any:
    """A config node as plain Python: lists resolved (their items are values), mappings as they are written."""
    if isinstance(value, ListConfig):
        return OmegaConf.to_container(value, resolve=True)
    if isinstance(value, DictConfig):
        return OmegaConf.to_container(value, resolve=False)
    return value


def _get(cfg: DictConfig, key: str) -> Any:
    """The value at a dotted key as plain Python, or _ABSENT (raises MissingMandatoryValue for ???)."""
    value = OmegaConf.select(cfg, key, default=_ABSENT, throw_on_missing=True)
    return value if value is _ABSENT else _plain(value)


def _apply(cfg: DictConfig, key: str, rule: Rule) -> str | None:
    try:
        value = _get(cfg, key)
    except MissingMandatoryValue:
        return f"{key}: is not set (??? in the config); set it to {rule.expected}: {key}=..."
    except OmegaConfBaseException as error:
        return f"{key}: cannot be read ({type(error).__name__}: {str(error).splitlines()[0]})"
    if value is _ABSENT:
        return None
    why = rule.test(value)
    return None if why is None else problem(key, rule.expected, value, why)



def _is_vlm(cfg: DictConfig) -> bool:
    """model.kind=vlm (model=vlm/<backend>; a bad kind is reported by check_task_kind)."""
    model = _get(cfg, "model")
    return isinstance(model, dict) and model.get("kind") == "vlm"


# task=profile (tasks/detector/profile.py)
def _family_list() -> Rule:
    """all, or a non-empty list of detector families (conf/model/*.yaml, the VLMs not among them)."""
    def test(value):
        from lanevil_train.tasks.detector.profile import detector_families

        if value == "all":
            return None
        if not is_list(value) or not value or not all(isinstance(x, str) for x in value):
            return ""
        unknown = [x for x in value if x not in detector_families()]
        return f"no detector family {', '.join(map(repr, unknown))}" if unknown else None
    return Rule("all or a list of detector families (laneatt, ufld, bezierlanenet, ganet, scnn, laneformer, clrnet, "
                "clrernet)", test)


RULES.update({
    "task.families": null_or(_family_list()),
    "task.input_size": null_or(int_pair(16)),
    "task.batch_size": integer(1),
    "task.warmup": null_or(integer(0)),
})

# Rules that differ by task (task.name): check_config applies them in place of RULES' for that task; None: the task
# does not read the key, which is not checked. task.runs lists run folders for task=report and task=compare, and
# counts the timed runs of task=profile; task=profile builds networks only, so an experiment=official_* config's
# dataset folder (data.root: ???) need not be given.
TASK_RULES: dict[str, dict[str, Rule | None]] = {
    "profile": {
        "data.root": None,
        "task.runs": null_or(integer(1)),
        "model.kind": Rule("detector (task=profile measures lane detectors: model=laneatt, ufld, bezierlanenet, ganet, "
                           "scnn, laneformer, clrnet or clrernet, or a detector's ckpt_path=; model=vlm/<backend> is a "
                           "VLM)",
                           lambda v: ok(v == "detector")),
    },
}


def task_rules(cfg: DictConfig) -> dict[str, Rule | None]:
    """The rules of TASK_RULES for the config's task.name (none for most tasks)."""
    name = _get(cfg, "task.name")
    return TASK_RULES.get(name, {}) if isinstance(name, str) else {}


# task=predict (tasks/detector/predict.py; the formats are predict/run.py FORMATS). It reads no dataset, so an
# experiment=official_* config's dataset folder (data.root: ???) need not be given.
def _existing_path() -> Rule:
    def test(value):
        if not isinstance(value, str) or not value:
            return ""
        from pathlib import Path

        return None if Path(value).exists() else "no such file or folder"
    return Rule("an image, a folder of images, a video or an image list (.txt) that exists", test)


RULES.update({
    "task.input": null_or(_existing_path()),
    "task.max_frames": null_or(integer(1)),
    "task.stride": integer(1),
    "task.format": one_of("tusimple", "culane", "both"),
    "task.write_frames": boolean(),
    "task.jpeg_quality": integer(1, 100),
    "task.illusion": null_or(one_of(*ILLUSIONS)),
    "task.severity": integer(1, 5),
    "task.seed": integer(0),
    "task.labels": null_or(existing_file("TuSimple label file")),
    **{f"task.{name}": rule for name, rule in IllusionSettings.SETTINGS.items()},  # their owner's ranges
})
TASK_RULES["predict"] = {"data.root": None}

# task=search (tasks/search.py): its own keys' rules are SearchSettings' (task.illusion must name one); the rest are
# task=closed_loop's, whose settings it reads
TASK_RULES["search"] = {f"task.{key}": rule for key, rule in SearchSettings.SETTINGS.items()}

# task=leaderboard (tasks/leaderboard.py): its keys' rules are report/leaderboard.py's own
RULES.update({f"task.{key}": rule for key, rule in LEADERBOARD_SETTINGS.items()})
