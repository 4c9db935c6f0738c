"""The `_target_` nodes: each must import, and each of its keys must be a parameter of what it names."""

from __future__ import annotations

import importlib
import inspect
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from lanevil_train.rules import (
    nearest,
    problem,
)
from lanevil_train.tasks.config_check.keys import HYDRA_KEYS, READ_BY_CODE, SPLITS, SUPPLIED
from lanevil_train.tasks.config_check.table import _is_vlm, _plain

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
            near = nearest(name, accepted)
            hint = f"did you mean {key}.{near}? " if near else ""
            problems.append(f"{key}.{name}: not a parameter of {target}; {hint}it accepts {', '.join(accepted)}")
    return problems
