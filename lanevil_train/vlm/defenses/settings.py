"""The settings of the textual defenses (defense=pat++, pat, self_reminder; `defense.*` in a config): which keys each
method reads and what a good value of each is. Owned here, beside the defenses: the VLM tasks build one typed
PromptDefense from them before any model loads and pass it down, and the config check reports a bad one by its key."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
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


@dataclass(frozen=True)
class PromptDefense:
    """A textual defense's settings (defense.* with a `prompt`), typed and checked once by ``from_settings`` and
    passed to what uses them. The keys its method does not read stay None."""

    name: str
    prompt: str
    before: str | None = None
    after: str | None = None
    alpha: float | None = None
    hard_target: str | None = None
    hardness: str | None = None
    pool_clips: int | None = None
    examples: int | None = None
    steps: int | None = None
    prefix_length: int | None = None
    suffix_length: int | None = None
    top_k: int | None = None
    num_candidates: int | None = None
    chunk: int | None = None
    soft: bool = False
    soft_lr: float | None = None
    prefix_path: str | None = None

    @classmethod
    def from_settings(cls, values: Mapping[str, Any], name: str) -> PromptDefense:
        """The defense of plain defense.* values (a config's `defense` node; `name` its config name); a ValueError
        lists every bad key, each named `defense.<key>`."""
        problems = prompt_problems(values)
        if problems:
            raise ValueError("; ".join(problems))
        method_keys = ("prompt",) + METHOD_KEYS[values["prompt"]] + ("prefix_path",)
        return cls(name=name, **{key: values[key] for key in method_keys if values.get(key) is not None})

    @property
    def tuned(self) -> bool:
        """Whether the method tunes a prefix (pat++, pat) rather than wrapping questions (self_reminder)."""
        return self.prompt in TUNED
