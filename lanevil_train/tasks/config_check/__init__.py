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

import re

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from lanevil_train.rules import Rule
from lanevil_train.tasks.config_check.config_rules import known_defenses
from lanevil_train.tasks.config_check.cross import CROSS_CHECKS
from lanevil_train.tasks.config_check.keys import TRAINING_KEYS
from lanevil_train.tasks.config_check.table import RULES, _apply, _get, task_rules
from lanevil_train.tasks.config_check.targets import _locate, _target_nodes, check_target

# what the rest of the package imports from here
__all__ = ["ConfigError", "RULES", "TRAINING_KEYS", "check_config", "head_rules",
           "interpolated_from", "known_defenses"]


class ConfigError(ValueError):
    """The composed config has bad values: one line per problem, each naming its key."""

    def __init__(self, problems: list[str], where: str = "the config"):
        self.problems = list(problems)
        count = f"{len(problems)} problem{'s' if len(problems) > 1 else ''}"
        super().__init__(f"{where} has {count}:\n" + "\n".join(f"  {p}" for p in self.problems))



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
    for key, rule in {**RULES, **head_rules(cfg), **task_rules(cfg)}.items():  # a task's own rules win (TASK_RULES)
        if rule is None:  # a key this task does not read
            continue
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
