"""Tasks: one function each, a composed config in, results out. Only tasks/ and cli.py see Hydra.

Each conf/task/<name>.yaml names its function with `_target_` (a dotted path); a new task is that
function plus that config (in the package, or in a user's `hydra.searchpath` folder).
"""

from __future__ import annotations

from omegaconf import DictConfig


def run_task(cfg: DictConfig) -> float | None:
    """Check the config's values (lanevil_train.tasks.config_check), then call the function cfg.task._target_
    names with the whole config; return what it returns."""
    from hydra.utils import get_method

    from lanevil_train.tasks.config_check import check_config

    check_config(cfg)  # a bad value fails here, naming its key, before any data is read or a step trained
    target = cfg.task.get("_target_")
    if not target:
        raise ValueError(f"task={cfg.task.get('name')}: the task config names no function; add e.g. "
                         f"`_target_: lanevil_train.tasks.train.train` to it")
    try:
        function = get_method(target)
    except Exception as error:  # Hydra wraps import failures in its own exception types
        raise ValueError(f"task._target_={target!r}: cannot import that function ({error})") from error
    return function(cfg)
