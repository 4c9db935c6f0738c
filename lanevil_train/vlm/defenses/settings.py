"""The settings of the textual defenses (defense=pat++, pat, self_reminder; `defense.*` in a config): which keys each
method reads and what a good value of each is. Owned here, beside the defenses: the VLM tasks check a defense's
settings with them before any model loads, and the config check reports a bad one by its key."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from lanevil_train.rules import Rule, boolean, existing_file, integer, null_or, number, one_of, settings_problems, text
from lanevil_train.vlm.defenses.pat import HARD_TARGETS

PROMPT_DEFENSES = ("pat++", "pat", "self_reminder")  # defense.prompt: the method
HARDNESS = ("accuracy", "judge", "language")  # how PAT++ finds hard examples (tasks/vlm/defense.choose_examples)
TUNED = ("pat++", "pat")  # the methods whose prefix is tuned into prefix.json

SETTINGS: dict[str, Rule] = {
    "prompt": one_of(*PROMPT_DEFENSES),
    "before": text(),
    "after": text(),
    "alpha": number(0, 1),
    "hard_target": one_of(*HARD_TARGETS),
    "hardness": one_of(*HARDNESS),
    **{key: integer(1) for key in ("pool_clips", "examples", "steps", "prefix_length", "suffix_length", "top_k",
                                   "num_candidates", "chunk")},
    "soft": boolean(),
    "soft_lr": number(0, low_open=True),
    "prefix_path": null_or(existing_file("prefix.json file")),
}

_GCG = ("alpha", "steps", "prefix_length", "top_k", "num_candidates", "chunk", "examples", "pool_clips")
# The keys each method needs (each must be present and good).
METHOD_KEYS = {"self_reminder": ("before", "after"), "pat": _GCG + ("suffix_length",),
               "pat++": _GCG + ("hard_target", "hardness", "soft", "soft_lr")}


def prompt_problems(settings: Mapping[str, Any]) -> list[str]:
    """What is wrong with a textual defense's settings (plain values; an absent key the method needs counts as
    null): every problem, each named `defense.<key>`."""
    method = settings.get("prompt")
    keys = ("prompt",) + METHOD_KEYS.get(method, ())
    return settings_problems({k: SETTINGS[k] for k in keys}, {k: settings.get(k) for k in keys}, "defense")
