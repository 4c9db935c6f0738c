"""Rules for the config's own kinds of value (suites, defenses, targets, checkpoints, rates), built on the shared
rules of lanevil_train/rules.py."""

from __future__ import annotations

import re
from pathlib import Path

from lanevil_train.checkpoints import archive_path
from lanevil_train.illusions import ILLUSIONS
from lanevil_train.lanes import check_culane_rows
from lanevil_train.rules import (
    Rule,
    existing_file,
    is_int,
    ok,
)
from lanevil_train.tasks.config_check.keys import DEFENSE_KEYS, PROMPT_DEFENSE_KEYS, SPLITS


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


def checkpoint_file(what: str = "checkpoint file") -> Rule:
    """An existing file, or a checkpoint inside one: ARCHIVE::member (a release archive's member,
    checkpoints.ARCHIVE_MEMBER)."""
    rule = existing_file(what)
    return Rule(rule.expected, lambda v: rule.test(str(archive_path(v)) if isinstance(v, str) and v else v))


def checkpoint_mapping() -> Rule:
    """task.models of task=closed_loop: {label: path of an existing checkpoint file}, possibly empty."""
    def test(v):
        if not isinstance(v, dict):
            return ""
        missing = [f"{label}: {path!r}" for label, path in v.items()
                   if not isinstance(path, str) or not archive_path(path).is_file()]
        return f"no such checkpoint file for {', '.join(missing)}" if missing else None
    return Rule("a mapping {label: checkpoint file}", test)


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


def mapping() -> Rule:
    """A mapping (its keys: the settings group's, table.SETTINGS_GROUPS)."""
    return Rule("a mapping", lambda v: ok(isinstance(v, dict)))


def rate_factors() -> Rule:
    def test(v):
        if not isinstance(v, dict):
            return ""
        bad = [f"{k}: {f!r}" for k, f in v.items() if isinstance(f, bool) or not isinstance(f, (int, float)) or f < 0]
        return f"factors must be numbers >= 0 ({', '.join(bad)})" if bad else None
    return Rule("a mapping {parameter name pattern: rate factor >= 0}, e.g. {'backbone.*': 0.1}", test)


def odd_box() -> Rule:
    """model.decode.blur: 0 (no blur) or an odd box side."""
    return Rule("0 (no blur) or an odd integer >= 1 (the blur box's side)",
                lambda v: None if isinstance(v, int) and not isinstance(v, bool) and (v == 0 or (v > 0 and v % 2))
                else "")


def culane_rows() -> Rule:
    """model.culane_rows: null or [start, stop, step] (lanes.check_culane_rows)."""
    def test(v):
        try:
            check_culane_rows(v)
        except ValueError:
            return ""
        return None
    return Rule("null (each lane's own points) or [start, stop, step], numbers with step > 0 and stop > start "
                "(the rows numpy.arange gives)", test)


def _for_splits(key: str, rule: Rule) -> dict[str, Rule]:
    """The same rule for data.train.<key>, data.val.<key> and data.test.<key>."""
    return {f"data.{split}.{key}": rule for split in SPLITS}
