"""Check the user-facing values of a composed config before any long work (dataset reading, rendering, training).

`check_config(cfg)` goes through RULES, a table of dotted key -> rule, then a few checks that look at two keys
at once (CROSS_CHECKS) and at every `_target_` node (it must import, and its keys must be parameters it
accepts). Every problem is collected; one ConfigError lists them all, one per line, e.g.

    data.input_size: expected [height, width], two integers >= 16, got [112]

A rule applies only when its key is in the composed config, so a data group without e.g. `root` is fine.
Only root-level paths are checked for existence (ckpt_path, task.init_from, backbone.checkpoint, data.root,
task.suite, defense.prefix_path); what is inside a file is for its reader. A detector defense's own parameters
(thresholds, probabilities) are checked by its constructor when it is built.
"""

from __future__ import annotations

import importlib
import inspect
import re
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue, OmegaConfBaseException

from lanevil_train.data.normalization import NORMALIZATIONS
from lanevil_train.illusions import ILLUSIONS, SEVERITIES
from lanevil_train.models.backbones import OUTPUT_STRIDES, indices_for_strides, stage_strides
from lanevil_train.models.head import decode_option_problems
from lanevil_train.models.schedules import LR_SCALINGS
from lanevil_train.perturbations import SUITE_KINDS, suite_names
from lanevil_train.progress import MODES
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
    is_int,
    is_number,
    null_or,
    number,
    ok,
    one_of,
    problem,
    string_list,
    text,
)
from lanevil_train.tasks.kinds import task_target
from lanevil_train.vlm.defenses.pat import HARD_TARGETS

# Keys of a `_target_` node that Hydra reads itself (not passed to the target).
HYDRA_KEYS = {"_target_", "_recursive_", "_convert_", "_partial_", "_args_"}
# Arguments the code passes to a target itself: a config value for them would be ignored.
SUPPLIED = {"model.head": ("in_channels", "in_strides", "image_size"), "model.neck": ("in_channels", "in_strides")}
# Keys of a target node that the code reads itself (not arguments of its target): a VLM's training settings.
# Keys of a VLM model node read by the training code, not arguments of its inference `_target_`.
TRAINING_KEYS = ("lora", "fine_tune", "embedded", "attention_layer")
READ_BY_CODE = {"model": (*TRAINING_KEYS, "kind")}
PROMPT_DEFENSES = ("pat++", "pat", "self_reminder")  # the textual defenses of VLMs (defense.prompt)
HARDNESS = ("accuracy", "judge", "language")  # how PAT++ finds hard examples (tasks/vlm/defense.choose_examples)
DEFENSE_KEYS = ("name", "transforms", "mixer", "callback")
# The keys of a textual defense of VLMs (defense=pat++: tasks/vlm/defense.py), beside DEFENSE_KEYS.
PROMPT_DEFENSE_KEYS = ("prompt", "alpha", "hard_target", "hardness", "pool_clips", "examples", "steps",
                       "prefix_length", "suffix_length", "top_k", "num_candidates", "chunk", "soft", "soft_lr",
                       "prefix_path", "before", "after")
SPLITS = ("train", "val", "test")


class ConfigError(ValueError):
    """The composed config has bad values: one line per problem, each naming its key."""

    def __init__(self, problems: list[str], where: str = "the config"):
        self.problems = list(problems)
        count = f"{len(problems)} problem{'s' if len(problems) > 1 else ''}"
        super().__init__(f"{where} has {count}:\n" + "\n".join(f"  {p}" for p in self.problems))


# ---------------------------------------------------------------------------------------------- rules

def api_key_variable() -> Rule:
    """null (no key) or the name of a set environment variable (vlm/http.py says what is wrong otherwise)."""
    from lanevil_train.vlm.http import api_key_problem

    return Rule("null (no key sent) or the name of a set environment variable holding the API key", api_key_problem)


def output_folder() -> Rule:
    """A folder to write into: it may exist (a rerun resumes there) but must not be a file."""
    def test(v):
        if not isinstance(v, str) or not v:
            return ""
        return "an existing file, not a folder" if Path(v).exists() and not Path(v).is_dir() else None
    return Rule("a folder path (new, or a folder to resume)", test)


def illusion_names() -> Rule:
    """task.illusions: 'all' or names of the suite's kind (illusions, or corruptions for a corruption suite; which
    kind is checked by check_suite_names)."""
    def test(v):
        if v == "all":
            return None
        if not isinstance(v, list) or not v or not all(isinstance(x, str) for x in v):
            return ""
        from lanevil_train.corruptions import CORRUPTIONS

        unknown = [x for x in v if x not in ILLUSIONS and x not in CORRUPTIONS]
        return (f"unknown: {', '.join(unknown)}; known: illusions {', '.join(ILLUSIONS)}; corruptions "
                f"{', '.join(CORRUPTIONS)}" if unknown else None)
    return Rule("'all' or a non-empty list of illusion (or, for a corruption suite, corruption) names", test)


def seed_list() -> Rule:
    """task.seeds: distinct integers >= 0, or empty."""
    return Rule("a list of distinct integers >= 0 (empty: one run with `seed`)",
                lambda v: ok(isinstance(v, list) and all(is_int(x) and x >= 0 for x in v) and len(set(v)) == len(v)))


ON_THE_FLY_SUITES = ("synthetic", "corruptions", "combined")  # generated per run: illusions, corruptions, pairs
SUITE_FILES = {"manifest.jsonl": "an illusion image set", "clips.jsonl": "a clip suite"}


def illusion_suite() -> Rule:
    """task.suite: null, synthetic, a set written by task=build (a directory holding manifest.jsonl, or clips.jsonl
    for VLM clips), or a DriveLM-style QA JSON file (VLMs)."""
    def test(v):
        if v is None or v in ON_THE_FLY_SUITES:
            return None
        if not isinstance(v, str) or not v:
            return ""
        if Path(v).is_file() and Path(v).suffix == ".json":
            return None
        if not Path(v).is_dir():
            return "no such directory"
        return None if any((Path(v) / name).is_file() for name in SUITE_FILES) else "it holds no manifest.jsonl"
    return Rule("null, synthetic (the illusion suite), corruptions, combined, a directory written by task=build "
                "(holding manifest.jsonl, or clips.jsonl for a VLM), or a DriveLM QA .json file", test)


def defense_keys() -> Rule:
    """The defense node: DEFENSE_KEYS, and PROMPT_DEFENSE_KEYS too when it is a textual defense (has `prompt`)."""
    def test(v):
        if not isinstance(v, dict):
            return ""
        unknown = sorted(set(v) - set(DEFENSE_KEYS) - set(PROMPT_DEFENSE_KEYS if "prompt" in v else ()))
        return f"unknown keys: {', '.join(unknown)}" if unknown else None
    return Rule(f"a mapping with the keys {', '.join(DEFENSE_KEYS)} (and, in a textual defense of VLMs, "
                f"{', '.join(PROMPT_DEFENSE_KEYS)})", test)


def known_defenses() -> list[str]:
    """The defense configs a run can compose: conf/defense/*.yaml, and those a hydra.searchpath folder adds (when
    Hydra is running)."""
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.hydra_config import HydraConfig

    import lanevil_train.conf

    if GlobalHydra.instance().is_initialized():
        overrides = [*HydraConfig.get().overrides.hydra, *HydraConfig.get().overrides.task] \
            if HydraConfig.initialized() else []
        return sorted(GlobalHydra.instance().config_loader().get_group_options("defense", config_name="config",
                                                                               overrides=overrides))
    return sorted(p.stem for p in (Path(lanevil_train.conf.__file__).parent / "defense").glob("*.yaml"))


def defense_names() -> Rule:
    """task.defenses of task=compare: names of defense configs, each once, `none` and at least one other (the
    configs are looked up when the rule runs, so a hydra.searchpath folder's count)."""
    def test(v):
        if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
            return ""
        known = known_defenses()
        unknown = [x for x in v if x not in known]
        if unknown:
            return f"unknown: {', '.join(unknown)}; known: {', '.join(known)}"
        if len(set(v)) < len(v):
            return "a name is listed twice"
        if "none" not in v:
            return "'none' is missing: it is the reference every gain is measured against"
        return None if len(v) >= 2 else "nothing to compare 'none' with"
    return Rule("a list of defense config names, each once, with none and at least one other", test)


def checkpoint_mapping() -> Rule:
    """task.models of task=closed_loop: {label: path of an existing checkpoint file}, possibly empty."""
    def test(v):
        if not isinstance(v, dict):
            return ""
        missing = [f"{label}: {path!r}" for label, path in v.items()
                   if not isinstance(path, str) or not Path(path).is_file()]
        return f"no such checkpoint file for {', '.join(missing)}" if missing else None
    return Rule("a mapping {label: checkpoint file}", test)


def number_range(low: float) -> Rule:
    """[a, b] with low <= a <= b (a range of numbers)."""
    return Rule(f"[low, high], two numbers with {low} <= low <= high",
                lambda v: ok(isinstance(v, list) and len(v) == 2 and all(is_number(x) for x in v)
                              and low <= v[0] <= v[1]))


def http_url() -> Rule:
    return Rule("an http(s) URL, e.g. http://127.0.0.1:8000/v1",
                lambda v: ok(isinstance(v, str) and re.match(r"^https?://[^\s/]+", v) is not None))


def integer_in(choices) -> Rule:
    return Rule(f"one of {', '.join(map(str, choices))}",
                lambda v: ok(isinstance(v, int) and not isinstance(v, bool) and v in choices))


def timm_model_name() -> Rule:
    def test(value):
        import timm

        return ok(isinstance(value, str) and timm.is_model(value))

    return Rule("a timm model name (resnet18, resnet34, resnet50, resnet101, vgg16, ...)", test)


def target_node() -> Rule:
    return Rule("a mapping with a _target_ (the dotted name of a class or function)",
                lambda v: ok(isinstance(v, dict) and isinstance(v.get("_target_"), str)))


def target_list() -> Rule:
    return Rule("a list of mappings, each with a _target_ (e.g. [{_target_: lanevil_train.illusions."
                "IllusionTransform, p: 0.3}])",
                lambda v: ok(isinstance(v, list) and all(target_node().test(x) is None for x in v)))


def mapping_of(keys: tuple[str, ...]) -> Rule:
    def test(v):
        if not isinstance(v, dict):
            return ""
        unknown = sorted(set(v) - set(keys))
        return f"unknown keys: {', '.join(unknown)}" if unknown else None
    return Rule(f"a mapping with the keys {', '.join(keys)}", test)


def rate_factors() -> Rule:
    def test(v):
        if not isinstance(v, dict):
            return ""
        bad = [f"{k}: {f!r}" for k, f in v.items() if isinstance(f, bool) or not isinstance(f, (int, float)) or f < 0]
        return f"factors must be numbers >= 0 ({', '.join(bad)})" if bad else None
    return Rule("a mapping {parameter name pattern: rate factor >= 0}, e.g. {'backbone.*': 0.1}", test)


def _for_splits(key: str, rule: Rule) -> dict[str, Rule]:
    """The same rule for data.train.<key>, data.val.<key> and data.test.<key>."""
    return {f"data.{split}.{key}": rule for split in SPLITS}


# Every user-facing value, by dotted key; a rule is skipped when its key is not in the composed config.
RULES: dict[str, Rule] = {
    # root
    "seed": integer(0, 2**32 - 1),
    "ckpt_path": null_or(existing_file("checkpoint file")),
    "progress": one_of(*MODES),
    # data
    "data.name": text(),
    "data.root": existing_dir("dataset directory"),
    "data.input_size": int_pair(16),
    "data.crop_top": number(0, 1, high_open=True),
    "data.normalize": one_of(*NORMALIZATIONS),
    "data.batch_size": integer(1),
    "data.num_workers": integer(0),
    "data.augment": boolean(),
    "data.max_lanes": integer(1),
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
    "model.lora": null_or(mapping_of(("r", "alpha", "dropout", "target_modules"))),
    "model.lora.r": integer(1),
    "model.lora.alpha": number(0, low_open=True),
    "model.lora.dropout": number(0, 1, high_open=True),
    "model.lora.target_modules": null_or(string_list()),
    "model.fine_tune": mapping_of(("lr", "weight_decay", "warmup_steps", "freeze_vision", "gradient_checkpointing",
                                   "train_eos", "variants", "aids")),
    "model.fine_tune.lr": number(0, low_open=True),
    "model.fine_tune.weight_decay": number(0),
    "model.fine_tune.warmup_steps": integer(0),
    "model.fine_tune.freeze_vision": boolean(),
    "model.fine_tune.gradient_checkpointing": boolean(),
    "model.fine_tune.train_eos": boolean(),
    "model.fine_tune.variants": one_of("all", "clean"),
    "model.fine_tune.aids": integer(0),
    "model.embedded.workers": any_of(one_of("auto"), integer(0)),
    "model.embedded.vision_pretraining": null_or(mapping_of(("steps", "clips", "batch", "lr", "mirror"))),
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
    "backbone.checkpoint": null_or(existing_file("state dict file")),
    "backbone.out_indices": null_or(int_list()),
    "backbone.output_stride": null_or(integer_in(OUTPUT_STRIDES)),  # which stages each backbone has: check_feature_map
    # defense (its parameters: the constructors)
    "defense": defense_keys(),
    "defense.name": text(),
    "defense.transforms": null_or(target_list()),
    "defense.mixer": null_or(target_node()),
    "defense.callback": null_or(target_node()),
    "defense.prompt": one_of(*PROMPT_DEFENSES),
    "defense.before": text(),
    "defense.after": text(),
    "defense.alpha": number(0, 1),
    "defense.hard_target": one_of(*HARD_TARGETS),
    "defense.hardness": one_of(*HARDNESS),
    **{f"defense.{key}": integer(1) for key in ("pool_clips", "examples", "steps", "prefix_length", "suffix_length",
                                                "top_k", "num_candidates", "chunk")},
    "defense.soft": boolean(),
    "defense.soft_lr": number(0, low_open=True),
    "defense.prefix_path": null_or(existing_file("prefix.json file")),
    # task (each task has some of these)
    "task.name": text(),
    "task.out_dir": null_or(output_folder()),
    "task.cases": integer(0),
    "task.frames": integer(1),
    "task.frame_step_m": number(0, low_open=True),
    "task.illusions": illusion_names(),
    "task.severities": int_list(SEVERITIES[0], SEVERITIES[-1]),
    "task.repeats": integer(1),
    "task.workers": integer(0),
    "task.fallback": boolean(),
    "task.test_after_fit": boolean(),
    "task.init_from": null_or(existing_file("checkpoint file")),
    "task.suite": illusion_suite(),
    "task.label": null_or(text()),
    "task.blind": boolean(),
    "task.baseline": null_or(text()),
    "task.runs": string_list(),
    "task.defenses": defense_names(),
    "task.seeds": seed_list(),
    "task.run_only": null_or(text()),
    "task.bootstrap": integer(100),
    "task.confidence": number(0, 1, low_open=True, high_open=True),
    "task.kind": one_of(*SUITE_KINDS),
    "task.onnx": null_or(existing_file("ONNX model written by task=export")),
    "task.out": null_or(text()),
    "task.opset": integer(9),
    "task.tolerance": number(0, low_open=True),
    "task.decode.conf_threshold": null_or(number(0, 1)),
    "task.decode.nms_threshold": null_or(number(0)),
    "task.decode.nms_topk": null_or(integer(1)),
    # task=closed_loop
    "task.policy": null_or(one_of("detector", "truth", "vlm")),
    "task.models": null_or(checkpoint_mapping()),
    "task.first_seed": integer(0),
    "task.start_before_m": number_range(0.0),
    "task.size": int_pair(32),
    "task.control_hz": number(0, 100, low_open=True),
    "task.window_s": number(0, low_open=True),
    "task.after_s": number(0),
    "task.threshold_m": number(0, low_open=True),
    "task.animate": boolean(),
    "task.vehicle.wheelbase_m": number(0.5, 10),
    "task.vehicle.speed_mph": number(0, 100, low_open=True),
    "task.vehicle.max_steer_deg": number(0, 80, low_open=True, high_open=True),
    "task.vehicle.max_steer_rate_dps": number(0, low_open=True),
    "task.controller.lookahead_s": number(0, low_open=True),
    "task.controller.min_lookahead_m": number(0, low_open=True),
    "task.controller.max_range_m": number(1),
    "task.controller.lane_width_m": number(2.0, 5.0),
    "task.vlm.question": text(),
    "task.vlm.steer_deg": number(0, 30, low_open=True, high_open=True),
    "task.vlm.frames": integer(1),
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


# ---------------------------------------------------------------------------------------------- values

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


def value_problem(key: str, value: Any) -> str | None:
    """The problem RULES[key] finds with `value` (a plain value, absent counts as None), else None: for code that
    checks a node of settings by the same rules outside a composed config."""
    rule = RULES[key]
    why = rule.test(value)
    return None if why is None else problem(key, rule.expected, value, why)


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


# ---------------------------------------------------------------------------------------------- cross-key checks

def check_feature_map(cfg: DictConfig) -> list[str]:
    """backbone.out_indices (or the stages of the family's model.feature_strides) must be stages the backbone has;
    data.input_size at least the largest stride the head reads, so each map has a row and a column (any size >=
    the stride works; a multiple of it is not needed)."""
    keys = ("backbone.name", "backbone.out_indices", "data.input_size", "model.feature_strides", "model.output_stride")
    values = tuple(_get(cfg, k) for k in keys)
    name, indices, size, wanted, output_stride = values
    if name is _ABSENT or any(RULES[k].test(v) is not None for k, v in zip(keys, values) if v is not _ABSENT):
        return []
    output_stride = _get(cfg, "backbone.output_stride") or (None if output_stride is _ABSENT else output_stride)
    if output_stride is _ABSENT or RULES["backbone.output_stride"].test(output_stride) is not None:
        return []
    strides = stage_strides(name, output_stride)
    n = len(strides)
    if indices in (None, _ABSENT):
        try:
            indices = indices_for_strides(name, wanted if wanted is not _ABSENT else [32], output_stride)
        except ValueError as error:
            return [f"{error} (set backbone.out_indices to choose the stages)"]
    elif not all(-n <= i < n for i in indices):
        return [problem("backbone.out_indices", f"stage indices of {name} from 0 to {n - 1} (strides "
                         f"{', '.join(map(str, strides))})", indices)]
    stride = max(strides[i] for i in indices)
    if RULES["data.input_size"].test(size) is None and min(size) < stride:
        return [f"{problem('data.input_size', f'[height, width], both >= {stride}', size)}: the head reads the "
                f"stride-{stride} feature map of {name} (backbone.out_indices {list(indices)}), which must have at "
                f"least one row and one column"]
    return []


def check_decode_options(cfg: DictConfig) -> list[str]:
    """model.decode may set only the decoding options of the family's head (its decode keywords). task.decode is
    checked against the checkpoint's family when it is loaded (tasks/detector/evaluate.load_checkpoint): the command
    line's model need not be the checkpoint's."""
    if _is_vlm(cfg):
        return []
    try:
        head = _locate(_get(cfg, "model.head._target_"))
    except Exception:  # a bad _target_ is reported by check_target
        return []
    node = _get(cfg, "model.decode")
    return decode_option_problems(head, node if isinstance(node, dict) else {}, "model.decode")


def check_backbone_weights(cfg: DictConfig) -> list[str]:
    if _get(cfg, "backbone.pretrained") is True and _get(cfg, "backbone.checkpoint") not in (None, _ABSENT):
        return ["backbone.checkpoint: give either backbone.pretrained=true (timm's download) or "
                "backbone.checkpoint=/path/to/weights.pth, not both"]
    return []


def check_cases(cfg: DictConfig) -> list[str]:
    """task.cases=0 means every dataset image, which only task=build on a real dataset has."""
    if _get(cfg, "task.cases") != 0:
        return []
    if _get(cfg, "task.name") == "build" and _get(cfg, "data.name") not in ("synthetic", "clips"):
        return []
    return [problem("task.cases", "an integer >= 1, the number of simulated scenes (0, every image, is only "
                     "for task=build on a real dataset)", 0)]


def suite_kind(cfg: DictConfig) -> str | None:
    """The kind of suite task.illusions names: task.kind of task=build, or the on-the-fly task.suite's."""
    if _get(cfg, "task.name") == "build":
        kind = _get(cfg, "task.kind")
        return "illusions" if kind is _ABSENT else kind
    if _get(cfg, "task.name") == "closed_loop":
        return "illusions"
    suite = _get(cfg, "task.suite")
    return {"synthetic": "illusions", "corruptions": "corruptions", "combined": "combined"}.get(suite) \
        if isinstance(suite, str) else None


def check_suite_names(cfg: DictConfig) -> list[str]:
    """task.illusions must name what the suite applies: illusions, or corruptions for a corruption suite; a
    combined suite needs illusions of two categories."""
    names, kind = _get(cfg, "task.illusions"), suite_kind(cfg)
    if names is _ABSENT or kind not in SUITE_KINDS or not (names == "all" or isinstance(names, list)):
        return []
    try:
        suite_names(kind, names)
    except ValueError as error:
        what = f"task.kind={kind}" if _get(cfg, "task.name") == "build" else f"task.suite={_get(cfg, 'task.suite')}"
        return [f"task.{error} ({what})"]
    return []


def _is_vlm(cfg: DictConfig) -> bool:
    """model.kind=vlm (model=vlm/<backend>; a bad kind is reported by check_task_kind)."""
    model = _get(cfg, "model")
    return isinstance(model, dict) and model.get("kind") == "vlm"


def check_task_kind(cfg: DictConfig) -> list[str]:
    """model.kind names a kind, and task=<name> has a function for that kind (tasks/kinds.py)."""
    try:
        task_target(cfg)
    except ValueError as error:
        return [str(error)]
    return []


def check_vlm_task(cfg: DictConfig) -> list[str]:
    """A VLM is evaluated on clips (task=evaluate) or reported (task=report); its suite is a clip suite."""
    if not _is_vlm(cfg):
        suite = _get(cfg, "task.suite")
        if isinstance(suite, str) and (Path(suite) / "clips.jsonl").is_file():
            return [problem("task.suite", "an illusion image set (manifest.jsonl) for a lane detector", suite,
                             "that is a VLM clip suite: evaluate it with model=vlm/<backend>")]
        return []
    task = _get(cfg, "task.name")
    if task in ("train", "compare") and _get(cfg, "model.base_url") is not _ABSENT:
        return [f"task: task=train with model={_get(cfg, 'model._target_')}: a model behind a server cannot be "
                f"trained here; fine-tune a local one (model=vlm/hf model.path=DIR, or model=vlm/embedded)"]
    embedded = _get(cfg, "model.embedded") not in (None, _ABSENT)
    if task in ("train", "compare") and _get(cfg, "data.name") != "clips":
        return [problem("data", "clips (a VLM trains on the clip suite's QA)", _get(cfg, "data.name"),
                         "model=vlm/<backend> selects data=clips unless another data= is given: drop it")]
    if task == "evaluate" and _get(cfg, "model.path") is None and _get(cfg, "ckpt_path") is None:
        what = "model=vlm/embedded is trained here" if embedded else "the model is loaded from a folder"
        return [f"model.path: {what}: give ckpt_path=<a task=train run's checkpoint> or model.path=<a saved "
                f"model folder, e.g. that run's model/>"]
    suite = _get(cfg, "task.suite")
    if isinstance(suite, str) and Path(suite).is_dir() and not (Path(suite) / "clips.jsonl").is_file():
        return [problem("task.suite", "a clip suite written by task=build data=clips (holding clips.jsonl), "
                         "synthetic, or a DriveLM QA .json file", suite, "a VLM answers questions about clips")]
    return []


def check_split_seeds(cfg: DictConfig) -> list[str]:
    """Simulated splits are seed ranges [first_seed, first_seed + num_scenes or num_cases): no two may overlap, or
    a model would be tested on scenes it was trained on."""
    ranges = []
    for split in SPLITS:
        first = _get(cfg, f"data.{split}.first_seed")
        count = _get(cfg, f"data.{split}.num_cases")
        count = _get(cfg, f"data.{split}.num_scenes") if count is _ABSENT else count
        if is_int(first) and is_int(count):
            ranges.append((split, first, first + count))
    problems = []
    for i, (a, a0, a1) in enumerate(ranges):
        for b, b0, b1 in ranges[i + 1:]:
            if a0 < b1 and b0 < a1:
                problems.append(f"data.{b}.first_seed: the {b} split's seeds [{b0}, {b1}) overlap the {a} split's "
                                f"[{a0}, {a1}); splits must not share scenes: move data.{b}.first_seed or shrink a "
                                f"split")
    return problems


def check_checkpoint_given(cfg: DictConfig) -> list[str]:
    task = _get(cfg, "task.name")
    if _is_vlm(cfg):
        return []  # a VLM backend loads its own weights (model.path, model.base_url)
    if task in ("evaluate", "cross_domain") and _get(cfg, "ckpt_path") is None \
            and _get(cfg, "task.onnx") in (None, _ABSENT):
        return [f"ckpt_path: task={task} scores a checkpoint; expected the path of a Lightning checkpoint file "
                f"(or task.onnx=model.onnx), got null"]
    if task == "closed_loop":
        policy = _get(cfg, "task.policy")
        if policy == "vlm":
            return ["task.policy: vlm needs a VLM: model=vlm/<backend> (e.g. model=vlm/embedded ckpt_path=...)"]
        if policy in (None, "detector") and _get(cfg, "ckpt_path") is None and not _get(cfg, "task.models"):
            return ["ckpt_path: task=closed_loop drives a trained detector; expected ckpt_path=<checkpoint>, "
                    "task.models={label: checkpoint, ...}, or task.policy=truth (the simulator's own lanes)"]
    return []


def check_training_ends(cfg: DictConfig) -> list[str]:
    if _get(cfg, "trainer.max_steps") == -1 and _get(cfg, "trainer.max_epochs") == -1:
        return ["trainer.max_epochs: -1 together with trainer.max_steps=-1 trains forever; set one of them, "
                "e.g. trainer.max_steps=1000"]
    return []


CROSS_CHECKS = (check_feature_map, check_decode_options, check_backbone_weights, check_cases, check_checkpoint_given,
                check_training_ends, check_task_kind, check_vlm_task, check_split_seeds, check_suite_names)


# ---------------------------------------------------------------------------------------------- _target_ nodes

# Where config nodes with a `_target_` are: single nodes, lists of them, and mappings of named ones.
TARGET_NODES = ("model", "model.head", "model.neck", "model.optimizer", "model.scheduler", "backbone", "defense.mixer",
                "defense.callback", "logger", "judge",
                *(f"data.{split}" for split in SPLITS))
TARGET_LISTS = ("data.train_transforms", "defense.transforms")
TARGET_MAPS = ("callbacks",)


def _target_nodes(cfg: DictConfig) -> list[tuple[str, DictConfig]]:
    """(dotted key, node) of every `_target_` node in the places above."""
    found = []
    for key in (*TARGET_NODES, *TARGET_LISTS, *TARGET_MAPS):
        try:
            node = OmegaConf.select(cfg, key)
        except OmegaConfBaseException:
            continue  # reported by its rule
        if key in TARGET_LISTS and isinstance(node, ListConfig):
            found += [(f"{key}[{i}]", item) for i, item in enumerate(node)]
        elif key in TARGET_MAPS and isinstance(node, DictConfig):
            found += [(f"{key}.{name}", item) for name, item in node.items_ex(resolve=False)]
        elif key in TARGET_NODES and (key not in ("model", "judge") or _is_vlm(cfg)):
            found.append((key, node))  # the model node is a _target_ node, and the judge used, for a VLM only
    return found


def _locate(path: str) -> Any:
    """The object a dotted path names: the longest importable module prefix, then attributes (as Hydra finds it)."""
    parts = path.split(".")
    for split in range(len(parts), 0, -1):
        module_name = ".".join(parts[:split])
        try:
            found = importlib.import_module(module_name)
        except ModuleNotFoundError as error:
            if error.name and (module_name == error.name or module_name.startswith(error.name + ".")):
                continue  # no such module: try a shorter prefix (the rest are attributes)
            raise  # the module exists but imports something that is not installed
        for attribute in parts[split:]:
            found = getattr(found, attribute)
        return found
    raise ModuleNotFoundError(f"No module named {parts[0]!r}")


def check_target(key: str, node: Any) -> list[str]:
    """The node's _target_ imports, and each of its keys is a parameter the target accepts."""
    if node is None or (isinstance(node, DictConfig) and node.get("_target_") is None and "_target_" in node):
        return []  # nothing to build (e.g. logger=none)
    if not isinstance(node, DictConfig) or not isinstance(node.get("_target_"), str):
        return [problem(key, "null or a mapping with a _target_ (the dotted name of a class or function)",
                         _plain(node))]
    target = node._target_
    try:
        built = _locate(target)
    except Exception as error:  # a missing module or attribute, or an error while importing the module
        return [f"{key}._target_: cannot import {target!r} ({type(error).__name__}: {error})"]
    try:
        parameters = inspect.signature(built).parameters
    except (TypeError, ValueError):
        return []  # no signature to check against
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values()):
        return []
    accepted = [n for n, p in parameters.items() if p.kind is not inspect.Parameter.VAR_POSITIONAL]
    problems = []
    for name in node:
        if name in READ_BY_CODE.get(key, ()):
            continue
        if name in SUPPLIED.get(key, ()):
            problems.append(f"{key}.{name}: is set by the code (from the backbone and data.input_size); remove it "
                            f"from the config")
        elif name not in HYDRA_KEYS and name not in accepted:
            problems.append(f"{key}.{name}: not a parameter of {target}; it accepts {', '.join(accepted)}")
    return problems


# ---------------------------------------------------------------------------------------------- entry point

def head_rules(cfg: DictConfig) -> dict[str, Rule]:
    """The rules of model.head.*: the SETTINGS of the head class model.head._target_ names (the head owns its ranges
    and checks them in its constructor; this reports them by key before any work)."""
    target = _get(cfg, "model.head._target_")
    if not isinstance(target, str):
        return {}
    try:
        head = _locate(target)
    except Exception:  # reported by check_target
        return {}
    return {f"model.head.{name}": rule for name, rule in getattr(head, "SETTINGS", {}).items()}


def interpolated_from(cfg: DictConfig, key: str) -> str | None:
    """The key whose value `key` copies (`${data.max_lanes}`), or None."""
    parent, _, leaf = key.rpartition(".")
    node = OmegaConf.select(cfg, parent) if parent else cfg
    if not isinstance(node, DictConfig) or not OmegaConf.is_interpolation(node, leaf):
        return None
    raw = OmegaConf.to_container(node, resolve=False)[leaf]
    match = re.fullmatch(r"\$\{([\w.]+)\}", raw)
    return match.group(1) if match else None


def check_config(cfg: DictConfig, where: str = "the config") -> None:
    """Raise ConfigError listing every bad user-facing value of `cfg` (one line each); return if all are good.

    A value copied from another key (`max_lanes: ${data.max_lanes}`) is reported at that key only. `where`
    names the config in the error's first line."""
    problems, bad_keys = [], set()
    for key, rule in {**RULES, **head_rules(cfg)}.items():
        problem = _apply(cfg, key, rule)
        if problem is not None:
            bad_keys.add(key)
            if interpolated_from(cfg, key) not in bad_keys:
                problems.append(problem)
    for check in CROSS_CHECKS:
        try:
            problems += [p for p in check(cfg) if p.split(":", 1)[0] not in bad_keys]
        except OmegaConfBaseException:
            pass  # a key it reads is unset or unreadable: its rule has said so
    for key, node in _target_nodes(cfg):
        if key.split("[")[0] not in bad_keys:  # a list item of a bad list is reported with its list
            problems += check_target(key, node)
    if problems:
        raise ConfigError(problems, where)
