"""Tasks: one function each, a composed config in, results out. Only tasks/ and cli.py see Hydra.

Each conf/task/<name>.yaml names its function with `_target_`: a dotted path, or one per kind of model
(`{detector: ..., vlm: ...}`, the kind being model.kind: tasks/kinds.py); a new task is that function plus that
config (in the package, or in a user's `hydra.searchpath` folder).
"""

from __future__ import annotations

from omegaconf import DictConfig

from lanevil_train.tasks.config_check import check_config
from lanevil_train.tasks.kinds import task_function


def run_task(cfg: DictConfig) -> float | None:
    """Check the config's values (lanevil_train.tasks.config_check), then call the function task._target_ names for
    the model's kind with the whole config; return what it returns."""
    check_config(cfg)  # a bad value fails here, naming its key, before any data is read or a step trained
    return task_function(cfg)(cfg)
