"""The kind of a run, decided once: the model config names its kind (`model.kind`: detector or vlm), and each
task config names the function that runs it for each kind (`task._target_`: one dotted name for a task that takes
any model, or a mapping kind -> dotted name). run_task picks the function here; the task functions do not ask
again, so the detector and VLM tasks are separate modules."""

from __future__ import annotations

from collections.abc import Callable, Mapping

from hydra.utils import get_method
from omegaconf import DictConfig

KINDS = ("detector", "vlm")


def model_kind(cfg: DictConfig) -> str:
    """cfg.model.kind, checked."""
    model = cfg.get("model")
    kind = model.get("kind") if isinstance(model, Mapping) else None
    if kind not in KINDS:
        raise ValueError(f"model.kind: expected one of {', '.join(KINDS)} (a lane detector's conf/model/<family>.yaml "
                         f"says `kind: detector`, a VLM backend's conf/model/vlm/<backend>.yaml `kind: vlm`), got "
                         f"{kind!r}")
    return kind


def is_vlm(cfg: DictConfig) -> bool:
    return model_kind(cfg) == "vlm"


def task_target(cfg: DictConfig) -> str:
    """The dotted name of the function that runs task=<name> for the model's kind."""
    name = cfg.task.get("name")
    target = cfg.task.get("_target_")
    if isinstance(target, Mapping):  # one function per kind of model
        kind = model_kind(cfg)
        if target.get(kind) is None:  # absent, or null (a task config that inherits another's and drops a kind)
            runs = " and ".join(f"{k} models" for k, function in target.items() if function is not None)
            raise ValueError(f"task: task={name} runs {runs}; this model is a {kind} (model.kind={kind})")
        target = target[kind]
    if not isinstance(target, str) or not target:
        raise ValueError(f"task={name}: the task config names no function; add e.g. "
                         f"`_target_: lanevil_train.tasks.detector.train.train` to it (or one per kind of model: "
                         f"`_target_: {{detector: ..., vlm: ...}}`)")
    return target


def task_function(cfg: DictConfig) -> Callable[[DictConfig], float | None]:
    """The function that runs task=<name> for the model's kind (task_target), imported."""
    target = task_target(cfg)
    try:
        return get_method(target)
    except Exception as error:  # Hydra wraps import failures in its own exception types
        raise ValueError(f"task._target_={target!r}: cannot import that function ({error})") from error
