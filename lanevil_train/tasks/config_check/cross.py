"""Checks that look at several keys at once (CROSS_CHECKS): feature maps and strides, decoding options, seeds of the
splits, the kind of task and model, what a task needs given."""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from lanevil_train.models.backbones import indices_for_strides, input_size_problem, stage_strides
from lanevil_train.models.head import decode_option_problems
from lanevil_train.perturbations import SUITE_KINDS, suite_names
from lanevil_train.rules import (
    is_int,
    is_number,
    problem,
    unknown_settings,
)
from lanevil_train.tasks.config_check.keys import SPLITS
from lanevil_train.tasks.config_check.table import _ABSENT, RULES, SETTINGS_GROUPS, _get, _is_vlm
from lanevil_train.tasks.config_check.targets import _locate
from lanevil_train.tasks.kinds import task_target


def check_feature_map(cfg: DictConfig) -> list[str]:
    """backbone.out_indices (or the stages of the family's model.feature_strides) must be stages the backbone has;
    data.input_size at least the largest stride the head reads, so each map has a row and a column (a multiple of
    it is not needed for most), and a size the backbone takes (a forward pass on the meta device: a ViT's patches
    must divide it, DLA's trees need a multiple of 32)."""
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
    if RULES["data.input_size"].test(size) is not None:
        return []
    if min(size) < stride:
        return [f"{problem('data.input_size', f'[height, width], both >= {stride}', size)}: the head reads the "
                f"stride-{stride} feature map of {name} (backbone.out_indices {list(indices)}), which must have at "
                f"least one row and one column"]
    why = input_size_problem(name, tuple(size), tuple(indices), output_stride)
    return [f"backbone.name: {name} cannot take data.input_size=[{size[0]}, {size[1]}]: {why}"] if why else []


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


def check_task_kind(cfg: DictConfig) -> list[str]:
    """model.kind names a kind, and task=<name> has a function for that kind (tasks/kinds.py)."""
    try:
        task_target(cfg)
    except ValueError as error:
        return [str(error)]
    return []


def check_vlm_task(cfg: DictConfig) -> list[str]:
    """A VLM is evaluated on clips (task=evaluate) or reported (task=report); its suite is a clip suite."""
    if _get(cfg, "task.name") == "audit_qa":
        return []  # it reads a QA file of any model's benchmark, never a model
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
    if task in ("closed_loop", "search"):
        policy = _get(cfg, "task.policy")
        if policy == "vlm":
            return ["task.policy: vlm needs a VLM: model=vlm/<backend> (e.g. model=vlm/embedded ckpt_path=...)"]
        if policy in (None, "detector") and _get(cfg, "ckpt_path") is None and not _get(cfg, "task.models"):
            return [f"ckpt_path: task={task} drives a trained detector; expected ckpt_path=<checkpoint>, "
                    "task.models={label: checkpoint, ...}, or task.policy=truth (the simulator's own lanes)"]
    return []


def check_training_ends(cfg: DictConfig) -> list[str]:
    if _get(cfg, "trainer.max_steps") == -1 and _get(cfg, "trainer.max_epochs") == -1:
        return ["trainer.max_epochs: -1 together with trainer.max_steps=-1 trains forever; set one of them, "
                "e.g. trainer.max_steps=1000"]
    return []


def check_acc_brakes(cfg: DictConfig) -> list[str]:
    """task.acc.decel_mps2 (the ACC's own braking) is at most task.vehicle.max_decel_mps2 (the brakes' limit)."""
    acc, brakes = _get(cfg, "task.acc.decel_mps2"), _get(cfg, "task.vehicle.max_decel_mps2")
    if is_number(acc) and is_number(brakes) and 0 < brakes < acc:  # a bad limit itself is its own rule's
        return [problem("task.acc.decel_mps2", f"at most task.vehicle.max_decel_mps2 ({brakes}, the brakes' limit)",
                        acc)]
    return []


def check_settings_groups(cfg: DictConfig) -> list[str]:
    """Every key of a settings group a class owns (SETTINGS_GROUPS: task.kalman, task.vehicle, model.lora, ...) is
    one of its settings: an unknown key (a typo Hydra's `+key=` let in) is named with the nearest and the valid."""
    problems = []
    for group, names in SETTINGS_GROUPS.items():
        values = _get(cfg, group)
        if isinstance(values, dict):
            problems += unknown_settings(names, values, group)
    return problems


CROSS_CHECKS = (check_settings_groups, check_feature_map, check_decode_options, check_backbone_weights, check_cases,
                check_checkpoint_given, check_training_ends, check_task_kind, check_vlm_task, check_split_seeds,
                check_suite_names, check_acc_brakes)
